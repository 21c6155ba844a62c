"""The evaluation protocol: one YAML file (``method_configs/eval/*.yaml``) loaded into dataclasses.

Relative paths in the YAML are resolved against the current working directory (like every ``ns-*`` command):
run ``ns-gsticker-eval`` from the repository root. Unknown keys are refused (a typo must not silently fall
back to a default), and every value is checked before anything runs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import yaml

from gsticker_plugin import attacks
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.recolor import palette as P

# The paper's numbers (Blender column; method.md). Kept here so that the tables print them beside ours.
PAPER = {
    "no_attack": 100.0,
    "noise": 99.25,
    "rotate": 98.87,
    "crop": 98.75,
    "blur": 99.88,
    "hue_jitter": 99.33,
    "clip_recolor": 99.50,
    "palette_recolor": 99.40,
    "color_baselines_after_recolor": "50-54",
    "psnr_wm_vs_original": 32.39,
    "ssim_wm_vs_original": 0.9713,
    "lpips_wm_vs_original": 0.0503,
    "psnr_vs_gt": {"vanilla-nerf": 27.44, "instant-ngp": 28.59, "tensorf": 29.18},
}
REFERENCE_COLORS = ("green", "yellow", "orange", "red", "pink", "magenta", "purple", "blue", "dodger blue", "cyan")
LEAKED_KEY = "leaked_key"
"""The curve of the white-box attack with a leaked owner key (strengths: PSNR budgets in dB)."""

ALL_STAGES = (
    "scene",
    "bases",
    "sticker",
    "renders",
    "quality",
    "geometry",
    "seeds",
    "distortions",
    "curves",
    "recolor",
    "purify",
    "false_positives",
    "speed",
    "wild",
    "report",
)


@dataclass
class SceneSpec:
    data: Optional[Path] = None
    """An existing dataset folder (Blender-format or nerfstudio-data)."""
    generate: Optional[Dict[str, Any]] = None
    """Or: generate the embedded scene with ns-gsticker-scene (keys: resolution, num_train, num_val, num_test, seed,
    layout: object or capture)."""


@dataclass
class BaseSpec:
    name: str
    """Row label and folder name (e.g. nerfacto, tensorf, vanilla-nerf)."""
    config: Optional[Path] = None
    """An existing base run (RUN/config.yml). When absent, the base is trained with ``preset``."""
    preset: Optional[str] = None
    """ns-train method used to train the base (gsticker-nerfacto-small, gsticker-tensorf-small, gsticker-vanilla-nerf-small, ...)."""
    steps: int = 2000
    """Training steps of the base when it is trained here."""
    args: List[str] = field(default_factory=list)
    """Extra ns-train arguments for the base."""
    paper_key: Optional[str] = None
    """Which of the paper's per-base PSNRs this row is compared with (vanilla-nerf, instant-ngp, tensorf)."""


@dataclass
class StickerSpec:
    steps: int = 1000
    """ns-train geometrysticker steps."""
    owner_id: str = "eval-owner"
    args: List[str] = field(default_factory=list)
    """Extra ns-train geometrysticker arguments (pool sizes, monitor cadence, ...)."""
    seeds: List[int] = field(default_factory=list)
    """The primary base's sticker trained again with these training seeds (ns-train --machine.seed; the main run has
    nerfstudio's default, 42): the seeds stage gives the spread of its model-level bit accuracy and PSNR."""


@dataclass
class DistortionRow:
    label: str
    """Row label (the paper's label where there is one)."""
    spec: str
    """Attack spec for gsticker_plugin.attacks.parse_attack_spec ('' = no attack), e.g. 'noise=0.1'."""
    paper: Optional[float] = None
    """The paper's bit accuracy (%) for this row, when it reports one."""


@dataclass
class FinetuneSpec:
    steps: int = 50
    color: Optional[str] = "blue"
    """Palette edit target (entry recolor.palette_entry set to this color); or hue_shift."""
    hue_shift: Optional[float] = None
    rays_per_step: int = 512
    steps_curve: List[int] = field(default_factory=list)
    """The same fine-tune read after these step counts too (a curve of bit accuracy against attack length; one
    fine-tune per model, snapshots written by ns-recolor finetune --save-at)."""
    max_views: Optional[int] = None
    """Training views the attacker renders as targets (ns-recolor's --max-views; null = its default, all 100)."""


@dataclass
class RecolorSpec:
    palette_entry: int = 0
    """Index of the palette entry (ordered by pixel share) that each reference color replaces."""
    colors: List[str] = field(default_factory=lambda: list(REFERENCE_COLORS))
    model_hue: List[float] = field(default_factory=lambda: [0.25, 0.5])
    """Model-level hue shifts (turns) applied with ns-recolor hue."""
    image_hue_jitter: Optional[float] = 0.5
    """Image-level hue jitter range (turns): each image shifted by U(-j, j) (per seed); null = skip."""
    finetune: Optional[FinetuneSpec] = field(default_factory=FinetuneSpec)
    keep_runs: bool = False
    """Keep the recolored runs (otherwise deleted once rendered; their renders are cached)."""


@dataclass
class FalsePositiveSpec:
    random_images: int = 64
    ground_truth: bool = True
    """Decode the scene's ground-truth test images (unmarked photos of the same scene)."""
    other_runs: List[Dict[str, Any]] = field(default_factory=list)
    """Unwatermarked runs of this or other scenes: [{name, config, data (optional)}]."""
    other_images: List[Path] = field(default_factory=list)
    """Folders of unmarked images (other scenes)."""


@dataclass
class GeometrySpec:
    """Model-level verdicts with the informed geometric decoder (``ns-verify-owner --decode geometry``)."""

    num_views: int = 8
    """Cameras per suspect model (as ns-verify-owner --num-views)."""
    sampled_share: float = 0.25
    """Share of those cameras sampled around the training views (the rest: the run's own cameras)."""
    purify_steps: List[int] = field(default_factory=lambda: [0, 100, 300, 1000])
    """Purification curve: fine-tune the *whole* watermarked model (density included) on clean training images,
    decoding after each of these cumulative step counts; [] = skip."""
    purify_lr: float = 1e-3
    purify_rays_per_step: int = 1024
    recolor_null: bool = True
    """Also decode every recolored *base* geometrically (its density is the base's, so all its bits are the
    undetermined-bit coin flips of the unwatermarked base; false = skip these decodes to save time)."""
    color_baseline: bool = True
    """Also build the color-branch baseline (the same sticker added to color instead of density, its amplitude
    matched to the sticker's PSNR) and decode it with the informed color decoder, unedited and after each recolor."""
    image_decoder: bool = True
    """Also read the image-level tables (distortions, curves, image hue jitter, image false positives) with the
    informed image decoder (``gsticker_plugin.decoders.image``: the owner's base and each test view's camera; the
    images quantized to 8 bits first), beside the blind extractor."""


@dataclass
class WildSpec:
    """Pictures found in the wild read without cameras (stage ``wild``), as registered in
    docs/experiments/images-wild-protocol.md: its seed, its views per row, its rows; null = skip the stage."""

    seed: int = 1621744754
    """The registered camera seed (never change it after a picture was read: draw a new one and say so)."""
    views: int = 24
    """Framed pictures per row."""
    development_views: List[int] = field(default_factory=lambda: [1, 2, 3])
    """Test views the image decoder was developed on: never drawn."""
    rows: List[str] = field(
        default_factory=lambda: [
            "framed",
            "rotation +-30",
            "hue +-0.5",
            "cropout 25 %",
            "noise 0.1",
            "JPEG 50",
            "blur 1",
            "resize 0.5",
            "crop + JPEG + hue",
        ]
    )
    """Rows of the shared run's pictures (:data:`gsticker_plugin.evaluation.wild.ROWS`); its recolored copies (the
    protocol's ``recolor`` edits) are read in the framed row."""
    null_seeds: List[int] = field(default_factory=lambda: [1, 2])
    """Independently trained bases of the scene in the null (``ns-train NULL_PRESET --machine.seed S``), read in the
    framed and JPEG 50 rows like the base."""
    null_preset: str = "gsticker-nerfacto-small"
    null_steps: int = 1000
    other_scene: bool = True
    """Also a base of another scene (``ns-gsticker-scene``, 100 px) in the null, its test views framed alike."""
    random_pictures: int = 32
    """Random null pictures (noise, smooth noise, flat colours, gradients) to make up the count: with the base's
    and the independent bases' 48 each, the other scene's 24 and the 24 photographs, 224 null pictures."""
    decode_seed: int = 20261209
    """The decoder's tie-breaking seed."""


@dataclass
class Protocol:
    name: str
    output_dir: Path
    scene: SceneSpec
    bases: List[BaseSpec]
    sticker: StickerSpec = field(default_factory=StickerSpec)
    num_views: int = 8
    """Test views rendered per model (evenly spaced over the test split)."""
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])
    """Seeds of the distortions' randomness (noise, cropout position, hue jitter); models are trained once."""
    fpr: float = 1e-6
    """Per-view false-positive rate of the verdict (48 bits: >= 41 matches)."""
    min_share: float = 0.5
    """Share of views that must pass for a model-level verdict (as ns-verify-owner)."""
    distortions: List[DistortionRow] = field(default_factory=list)
    curves: Dict[str, List[float]] = field(default_factory=dict)
    """Where-it-breaks curves: attack name -> strengths; ``leaked_key`` -> PSNR budgets in dB (PGD on the image
    decoder by someone holding the owner key and the base: ``gsticker_plugin.evaluation.leaked_key.leaked_key_attack``)."""
    recolor: Optional[RecolorSpec] = field(default_factory=RecolorSpec)
    false_positives: FalsePositiveSpec = field(default_factory=FalsePositiveSpec)
    geometry: Optional[GeometrySpec] = field(default_factory=GeometrySpec)
    """Model-level geometric decoding (the verdict that survives recoloring); null = skip."""
    wild: Optional[WildSpec] = None
    """Pictures found in the wild (stage ``wild``); null (the default) = skip."""
    device: str = "cpu"
    source: Optional[Path] = None
    """The YAML file this protocol came from."""


def _build(cls, data: Any, where: str):
    if data is None:
        return None
    if not isinstance(data, dict):
        raise GStickerError(f"{where}: expected a mapping of {cls.__name__} fields, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise GStickerError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(names))}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        v = data[f.name]
        sub = {
            "scene": SceneSpec,
            "sticker": StickerSpec,
            "recolor": RecolorSpec,
            "finetune": FinetuneSpec,
            "false_positives": FalsePositiveSpec,
            "geometry": GeometrySpec,
            "wild": WildSpec,
        }.get(f.name)
        if sub is not None and cls in (Protocol, RecolorSpec):
            v = _build(sub, v, f"{where}.{f.name}")
        elif f.name == "bases" and cls is Protocol:
            if not isinstance(v, list) or not v:
                raise GStickerError(f"{where}.bases: give a non-empty list of bases")
            v = [_build(BaseSpec, b, f"{where}.bases[{i}]") for i, b in enumerate(v)]
        elif f.name == "distortions" and cls is Protocol:
            v = [_build(DistortionRow, r, f"{where}.distortions[{i}]") for i, r in enumerate(v or [])]
        elif f.name in ("output_dir", "data", "config") and v is not None:
            v = Path(str(v))
        elif f.name == "other_images":
            v = [Path(str(p)) for p in (v or [])]
        kwargs[f.name] = v
    try:
        return cls(**kwargs)
    except TypeError as e:
        raise GStickerError(f"{where}: {e}") from None


def validate(p: Protocol) -> None:
    if (p.scene.data is None) == (p.scene.generate is None):
        raise GStickerError("scene: give exactly one of scene.data (a dataset folder) or scene.generate (settings)")
    names = [b.name for b in p.bases]
    if len(set(names)) != len(names):
        raise GStickerError(f"bases: names must be distinct, got {names}")
    for b in p.bases:
        if b.config is None and not b.preset:
            raise GStickerError(f"bases[{b.name}]: give config (an existing run) or preset (an ns-train method)")
        if b.config is not None and not Path(b.config).is_file():
            raise GStickerError(
                f"bases[{b.name}].config {b.config} does not exist (paths are relative to the "
                "current folder: run from the repository root)"
            )
    if p.num_views < 1:
        raise GStickerError(f"num_views must be >= 1, got {p.num_views}")
    if not p.seeds:
        raise GStickerError("seeds: give at least one seed")
    if len(set(p.sticker.seeds)) != len(p.sticker.seeds) or 42 in p.sticker.seeds:
        raise GStickerError(
            f"sticker.seeds: give distinct training seeds other than 42 (the main run's), got {p.sticker.seeds}"
        )
    if p.sticker.seeds and p.geometry is None:
        raise GStickerError("sticker.seeds needs geometry (the seeds stage decodes with the geometric decoder)")
    if not 0 < p.fpr < 1 or not 0 < p.min_share <= 1:
        raise GStickerError(f"fpr must be in (0,1) and min_share in (0,1], got {p.fpr}, {p.min_share}")
    try:
        for r in p.distortions:
            attacks.parse_attack_spec(r.spec)
        for name, strengths in p.curves.items():
            if name == LEAKED_KEY:
                if p.geometry is None or not p.geometry.image_decoder:
                    raise ValueError(
                        f"curves.{LEAKED_KEY} attacks the informed image decoder: it needs geometry with "
                        "image_decoder: true"
                    )
                if not strengths or any(float(s) <= 0 for s in strengths):
                    raise ValueError(f"curves.{LEAKED_KEY}: give PSNR budgets in dB > 0, weakest (highest) first")
                continue
            if name not in attacks.ATTACKS:
                raise ValueError(
                    f"curves: unknown attack {name!r}; use one of {', '.join(attacks.ATTACK_NAMES)} or {LEAKED_KEY}"
                )
            if not strengths:
                raise ValueError(f"curves.{name}: give at least one strength")
            for s in strengths:
                attacks.check_strength(name, float(s))
    except ValueError as e:
        raise GStickerError(str(e)) from None
    if p.recolor is not None:
        try:
            for c in p.recolor.colors:
                P.parse_color(c)
            for s in p.recolor.model_hue:
                P.check_hue_shift(float(s))
        except Exception as e:
            raise GStickerError(f"recolor: {e}") from None
        ft = p.recolor.finetune
        if ft is not None and (ft.color is None) == (ft.hue_shift is None):
            raise GStickerError("recolor.finetune: give exactly one of color or hue_shift")
    g = p.geometry
    if g is not None:
        if g.num_views < 1 or not 0 <= g.sampled_share <= 1:
            raise GStickerError(
                f"geometry: num_views must be >= 1 and sampled_share in [0, 1], got {g.num_views}, {g.sampled_share}"
            )
        if any(int(s) < 0 for s in g.purify_steps) or list(g.purify_steps) != sorted(g.purify_steps):
            raise GStickerError(f"geometry.purify_steps: give increasing step counts >= 0, got {g.purify_steps}")


def load_protocol(
    path: Path,
    output_dir: Optional[Path] = None,
    data: Optional[Path] = None,
    sticker_seeds: Optional[Sequence[int]] = None,
) -> Protocol:
    """Read and check a protocol YAML; ``output_dir``/``data``/``sticker_seeds`` override the file's values."""
    path = Path(path)
    if not path.is_file():
        raise GStickerError(
            f"--config {path} does not exist; pass a protocol YAML such as method_configs/eval/smoke.yaml"
        )
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise GStickerError(f"{path} is not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise GStickerError(f"{path}: expected a mapping at the top level")
    raw.setdefault("name", path.stem)
    raw.setdefault("output_dir", f"outputs/eval/{raw['name']}")
    for key in ("scene", "bases"):
        if key not in raw:
            raise GStickerError(f"{path}: missing required key {key!r}")
    p = _build(Protocol, raw, path.name)
    p.source = path
    if output_dir is not None:
        p.output_dir = Path(output_dir)
    if data is not None:
        p.scene = SceneSpec(data=Path(data))
    if p.scene.data is not None and not Path(p.scene.data).is_dir():
        raise GStickerError(f"scene.data {p.scene.data} is not a folder (paths are relative to the current folder)")
    if sticker_seeds is not None:
        p.sticker.seeds = [int(x) for x in sticker_seeds]
    validate(p)
    return p


def to_plain(obj: Any) -> Any:
    """Dataclasses/Paths as JSON-friendly values."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, dict):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    return obj
