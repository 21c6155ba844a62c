"""The options of each ``ns-recolor`` edit (light: parsing them imports no model code)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Tuple

import tyro
from typing_extensions import Annotated

PALETTE_METHOD = "gsticker-palette"


HUE_METHOD = "gsticker-hue"


@dataclass
class _Common:
    load_config: Path
    """The run to recolor: RUN/config.yml of any NeRF-style Nerfstudio run (stock, geometrysticker, recolored)."""
    output_dir: Optional[Path] = None
    """Where the new run is written (a new folder; refused if it exists unless --overwrite)."""
    data: Optional[Path] = None
    """The run's dataset folder, when the path recorded in its config does not exist from here."""
    overwrite: bool = False
    """Replace an existing --output-dir."""
    seed: int = 0
    """Seed of palette k-means, ray sampling and image-level jitter (same seed: same result)."""


@dataclass
class PaletteEdit:
    k: Optional[int] = None
    """Palette size (3..8); default: chosen per scene (elbow of the k-means curve)."""
    source: Literal["images", "renders"] = "images"
    """Extract the palette from the training images' foreground (alpha > 0.5) or from the model's renders."""
    set_: Annotated[Tuple[str, ...], tyro.conf.arg(name="set")] = ()
    """Edits INDEX=COLOR, e.g. --set 2=#1E90FF 0=red (names: green yellow orange red pink magenta purple blue
    'dodger blue' cyan, or any CSS name)."""
    palette: Tuple[str, ...] = ()
    """A whole edited palette, one color per entry ('keep' leaves an entry)."""
    softness: float = 5.0
    """Width (Lab dE) of the soft assignment of colors to palette entries."""
    max_views: int = 100
    """Training views used for the palette."""


@dataclass
class PaletteArgs(PaletteEdit, _Common):
    """Extract a palette of K colors and write a run whose fields' colors are re-mixed with the edited palette."""

    list_: Annotated[bool, tyro.conf.arg(name="list")] = False
    """Print the palette and write a swatch PNG (--swatch), write no run."""
    swatch: Optional[Path] = None
    """Swatch PNG for --list (default: palette.png in the current folder)."""


@dataclass
class HueArgs(_Common):
    """Model-level hue rotation (a new run), or --image-level hue jitter of rendered images."""

    shift: float = 0.25
    """Hue shift in turns, -0.5..0.5 (0.5 = 180 degrees). With --image-level: the jitter range +-|shift|."""
    image_level: bool = False
    """Render the run's views and jitter each image's HSV hue by a random shift in +-|shift| (the paper's color
    jitter); writes PNGs to --output-dir instead of a run."""
    fixed: bool = False
    """--image-level: shift every image by exactly --shift instead of a random jitter."""
    split: Literal["train", "val", "test"] = "test"
    """--image-level: which views to render."""
    limit: Optional[int] = None
    """--image-level: render at most this many views."""


@dataclass
class FinetuneArgs(PaletteEdit, _Common):
    """Fine-tune only the color branch (density frozen) toward recolored targets; writes the attacked run."""

    targets: Optional[Path] = None
    """A folder of edited images, one per training view (named like the training images, or in their order)."""
    hue_shift: Optional[float] = None
    """Targets = the run's training views hue-rotated by this many turns (model-level)."""
    steps: int = 200
    """Optimizer steps."""
    lr: float = 5e-3
    """Adam learning rate of the color parameters."""
    rays_per_step: int = 1024
    """Rays per step (random pixels of random training views)."""
    save_at: Tuple[int, ...] = ()
    """Also write the run as it is after each of these step counts (each below --steps) to OUT-stepN beside
    --output-dir: an attack-length curve from one fine-tune (the first N steps are those of an N-step run)."""
