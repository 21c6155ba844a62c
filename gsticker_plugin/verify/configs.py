"""The options of each ``ns-verify-owner`` subcommand (light: parsing them imports no model code)."""

from __future__ import annotations

EXIT_OWNED, EXIT_NOT_SHOWN, EXIT_ERROR = 0, 1, 2
"""ns-verify-owner's exit statuses: owned, not shown, error (never a verdict)."""

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Tuple


@dataclass
class VerifyConfig:
    """Decide whether a suspect run or a folder of suspect images carries an owner's message.

    Exit status: 0 "owned", 1 "not shown", 2 error. Calibrate a key's empirical null first with
    `ns-verify-owner calibrate --key KEY` (see docs/verify.md).
    """

    load_config: Optional[Path] = None
    """RUN/config.yml of the suspect run (any Nerfstudio method, recolored or not); N views are rendered."""
    images: Optional[Path] = None
    """Folder (searched recursively) or single file of suspect images: renders, screenshots, any size or format
    OpenImageIO reads. Files that cannot be used are skipped and listed in the report."""
    key: Optional[Path] = None
    """The owner key (.gskey written by ns-train geometrysticker)."""
    keys: Optional[Path] = None
    """A folder of owner keys (*.gskey): every key is tested, corrected for multiple testing (--correction)."""
    num_views: int = 24
    """Views rendered from a run (--load-config): its own cameras and sampled orbit poses."""
    sampled_share: float = 0.5
    """Share of the rendered views taken from sampled orbit poses; the rest are the run's own train/eval cameras."""
    data: Optional[Path] = None
    """Dataset folder of the run, when the path recorded in its config.yml does not exist from here (also used for
    the owner's base run under --decode geometry when its recorded dataset does not exist and --base-data is unset)."""
    decode: Literal["auto", "geometry", "image", "extractor"] = "auto"
    """geometry: informed decoding from the suspect model's accumulation/depth, given the owner's unwatermarked base
    run (needs a version-2 key and --load-config; model-level only); image: informed decoding of --images, given the
    owner's base run (the same fit on colour), at the cameras of --cameras or, without it, at cameras found by a
    search against the base (about 20 s a 100 px image on a CPU); extractor: the key's CNN reads the message from RGB
    renders or images (blind); auto: geometry for a model and image for images when the keys' base runs are
    reachable, else extractor."""
    cameras: Optional[Path] = None
    """--images only: a transforms JSON (Blender format, e.g. the base dataset's transforms_test.json) giving each
    image's camera, matched by file name without extension (r_0.png <-> ./test/r_0); without it the image decoder
    finds each image's camera itself. Images without a camera in the file are skipped and listed."""
    rolls: Tuple[float, ...] = (0.0,)
    """--images without --cameras: turns of each image about its centre (degrees) tried by the camera search, e.g.
    -30 -20 -10 0 10 20 30 for images that may have been rotated after rendering (each one adds the search's
    candidates again: slower)."""
    view_bank: bool = True
    """--images without --cameras: keep the camera search's renders of the owner's base beside the key
    (KEY.gskey.viewbank/, named by a hash of the base and the search) and reuse them on later calls; --no-view-bank
    renders them on every call."""
    base_config: Optional[Path] = None
    """The owner's base run (config.yml) for --decode geometry, when the path recorded in the key moved."""
    base_data: Optional[Path] = None
    """Dataset folder of the owner's base run, when its recorded one does not exist from here (default: --data)."""
    fpr: float = 1e-6
    """Per-view false-positive rate of the binomial test (1e-6 = at least 41 of 48 bits)."""
    min_share: float = 0.5
    """Share of views that must pass for the model-level verdict; its FPR is at most fpr / min-share."""
    correction: Literal["holm", "bonferroni"] = "holm"
    """Multiple-testing correction across keys (--keys)."""
    attack: str = ""
    """Distortions applied before decoding, in order, e.g. 'noise=0.1,rotate=30,crop=0.25,blur=1,jpeg=50,hue=0.3'."""
    seed: int = 0
    """Seed of the sampled poses and of the random attacks."""
    output: Path = Path("verify-report")
    """Folder for report.json and report.png (created; an existing report there is replaced)."""
    figure: bool = True
    """Write report.png (histogram of matches against the null and a few decoded views)."""
    max_side: int = 400
    """Images whose longer side exceeds this are downscaled (area average, streamed) to this size before decoding."""
    min_side: int = 16
    """Images with a shorter side below this are skipped (too small to carry a mark)."""
    max_pixels: int = 1_000_000_000
    """Images with more pixels than this are skipped (decompression-bomb guard); smaller ones are streamed."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Device for rendering and decoding (auto: cuda when available)."""
    progress: bool = True
    """Show tqdm progress bars (on stderr)."""
    commitment: Optional[str] = None
    """The commitment (hex) printed by `ns-verify-owner commit` and published when the model was released: checked
    against --key (a mismatch is an error, exit 2); the report says it matched, i.e. this key existed then."""
    public_key: Optional[str] = None
    """The owner's Ed25519 public key (hex) printed by `ns-verify-owner commit` and published with the commitment:
    the key's signature of its commitment must verify under it (else an error, exit 2)."""
    allow_legacy: bool = False
    """Read version-1 and version-2 keys, which have no integrity check (anyone can rewrite them)."""


@dataclass
class CalibrateConfig:
    """Decode unmarked renders/images with a key and store the observed null in the key.

    The key is rewritten atomically (HMAC recomputed, its commitment and signature unchanged); the previous file is kept as KEY.gskey.bak.
    """

    key: Path
    """The owner key to calibrate (.gskey)."""
    load_config: Tuple[Path, ...] = ()
    """Unmarked runs (config.yml) to render: other scenes, other models. GeometrySticker runs are rendered with the
    sticker off (i.e. their unmarked base)."""
    images: Tuple[Path, ...] = ()
    """Folders of unmarked images."""
    base: bool = True
    """Also render the base run the key was made on (the config path recorded in the key), when it exists here."""
    decode: Literal["extractor", "geometry", "image"] = "extractor"
    """Which decoder's null to measure: the extractor's (stored in the key's null), the geometric decoder's
    (stored in the key's geometry reference; decodes the base itself and the --load-config runs, not images) or the
    image decoder's (stored beside it; decodes the --images at the cameras of --cameras, e.g. the base dataset's
    own photos: unmarked images at known cameras; random images are not used)."""
    cameras: Optional[Path] = None
    """--decode image: the transforms JSON giving the cameras of the --images (Blender format)."""
    base_config: Optional[Path] = None
    """--decode geometry: the owner's base run (config.yml), when the path recorded in the key moved."""
    data: Optional[Path] = None
    """--decode geometry: dataset folder of the owner's base run, when its recorded one does not exist here."""
    random_images: int = 64
    """Random images (noise, smooth noise, flat colours, gradients) added to the null."""
    random_size: int = 64
    """Side of the random images."""
    num_views: int = 24
    """Views rendered per run."""
    sampled_share: float = 0.5
    """Share of the rendered views taken from sampled orbit poses."""
    append: bool = False
    """Add to the null already stored in the key instead of replacing it."""
    backup: bool = True
    """Keep the previous key file as KEY.gskey.bak before rewriting it."""
    seed: int = 0
    """Seed of the sampled poses and the random images."""
    max_side: int = 400
    """Images whose longer side exceeds this are downscaled before decoding."""
    min_side: int = 16
    """Images with a shorter side below this are skipped."""
    max_pixels: int = 1_000_000_000
    """Images with more pixels than this are skipped."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Device for rendering and decoding."""
    progress: bool = True
    """Show tqdm progress bars (on stderr)."""
    allow_legacy: bool = False
    """Read a version-1 or version-2 key, which has no integrity check (it is rewritten as a current key)."""


@dataclass
class ExportKeyConfig:
    """Add the geometry reference (the sticker, the gates) of a watermarked run to its owner key: a version-1 key
    becomes a version-2 key that `ns-verify-owner --decode geometry` can use. The run must carry the key's
    message and be made on the key's base."""

    load_config: Path
    """The watermarked run (RUN/config.yml written by ns-train geometrysticker) the key belongs to."""
    key: Path
    """The owner key (.gskey) to extend."""
    output: Optional[Path] = None
    """Where the extended key is written (default: the key itself, the previous file kept as KEY.gskey.bak)."""
    data: Optional[Path] = None
    """Dataset folder of the run, when the path recorded in its config.yml does not exist from here."""
    backup: bool = True
    """Keep the previous key file as KEY.gskey.bak when rewriting it in place."""
    allow_legacy: bool = False
    """Read a version-1 or version-2 key, which has no integrity check (the export rewrites it as a current key)."""


@dataclass
class CommitConfig:
    """Print the commitment of an owner key and the owner's public key (64 hex digits each, one a line) to publish or
    timestamp together when the model is released. Later, `ns-verify-owner --commitment HEX --public-key HEX --key
    KEY` shows this key existed then and was signed by the holder of that public key's identity (docs/verify.md)."""

    key: Path
    """The owner key (.gskey) to commit to."""
