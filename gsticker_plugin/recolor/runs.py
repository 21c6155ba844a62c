"""Reading the input run, checking the output folder, building and writing recolored runs, rendering views.

Every run written here has the layout Nerfstudio's own tools read: ``RUN/config.yml`` (whose output_dir,
experiment_name, method_name and timestamp name ``RUN``) and ``RUN/nerfstudio_models/step-N.ckpt``, so stock
``eval_setup``, ``ns-viewer``, ``ns-render`` (and gsticker's verifier) open it. The step is the wrapped run's
(TensoRF sizes its grids from it). Runs are written into a temporary sibling folder and renamed when complete.
"""

from __future__ import annotations

import copy
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
import yaml
from nerfstudio.engine.trainer import TrainerConfig
from torch import Tensor
from tqdm import tqdm

from gsticker_plugin import runs
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.key import file_sha256
from gsticker_plugin.model import shareable_state
from gsticker_plugin.recolor.model import RecolorModelConfig
from gsticker_plugin.runs import copy_datamanager, latest_checkpoint

# ---------------------------------------------------------------------------------------------- paths


def check_input_config(load_config: Path) -> Tuple[Any, Path, Path]:
    """(run config, run folder, latest checkpoint) of ``--load-config RUN/config.yml``."""
    p = Path(load_config)
    if not p.is_file():
        raise GStickerError(f"--load-config {p} does not exist; pass a trained run's RUN/config.yml")
    run_cfg = runs.load_run_config(p)

    if not isinstance(run_cfg, TrainerConfig):
        raise GStickerError(f"{p} is not a Nerfstudio run config; pass a trained run's RUN/config.yml")
    run_dir = p.resolve().parent
    ckpt = latest_checkpoint(run_dir / "nerfstudio_models")
    if ckpt is None:
        raise GStickerError(
            f"no checkpoint in {run_dir / 'nerfstudio_models'}; point --load-config at the config.yml "
            "of a trained run (with its nerfstudio_models/step-N.ckpt beside it)"
        )
    return run_cfg, run_dir, ckpt


def _inside(a: Path, b: Path) -> bool:
    """a == b or a lies inside b."""
    try:
        a.relative_to(b)
        return True
    except ValueError:
        return False


def check_output_dir(output_dir: Optional[Path], run_dir: Path, overwrite: bool) -> Path:
    if output_dir is None:
        raise GStickerError(
            "no output folder given; pass --output-dir OUT (a new folder; the input run is never changed)"
        )
    out = Path(output_dir).expanduser().resolve()
    run_dir = run_dir.resolve()
    if _inside(out, run_dir):
        raise GStickerError(
            f"--output-dir {output_dir} is inside the input run {run_dir}; the input run is never "
            "overwritten: pass an --output-dir outside it"
        )
    if _inside(run_dir, out):
        raise GStickerError(
            f"--output-dir {output_dir} contains the input run {run_dir}; the input run is never "
            "overwritten: pass another --output-dir"
        )
    blocker = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise GStickerError(
            f"--output-dir {output_dir} cannot be a folder: {blocker} is a file; pass another --output-dir"
        )
    if out.exists() and not overwrite:
        raise GStickerError(f"output folder {out} exists; pass --overwrite to replace it, or another --output-dir")
    return out


class StagedDir:
    """Write into a temporary sibling of ``final`` and move it in place on success (replacing an old one)."""

    def __init__(self, final: Path) -> None:
        self.final = final
        final.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))

    def commit(self) -> Path:
        if self.final.exists():
            shutil.rmtree(self.final)
        os.replace(self.tmp, self.final)
        return self.final

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


def run_location(config, out: Path, method_name: str, timestamp: str) -> Path:
    """Point ``config`` at ``out/<experiment>/<method>/<timestamp>`` (Nerfstudio's layout); returns that folder."""
    return runs.relocate(config, out, config.experiment_name or "recolor", method_name, timestamp)


# ---------------------------------------------------------------------------------------------- loading


@dataclass
class LoadedRun:
    config: Any  # the run's TrainerConfig (with --data applied)
    pipeline: Any
    run_dir: Path
    checkpoint: Path
    step: int


def data_override(run_cfg, data: Optional[Path]):
    """The run's datamanager config as a single-process VanillaDataManagerConfig, with ``--data`` applied."""
    return copy_datamanager(run_cfg, data)


def load_model_state(ckpt: Path) -> Tuple[Dict[str, Any], int]:
    state = runs.load_checkpoint_state(ckpt)
    return runs.model_state_from_pipeline_state(state["pipeline"]), int(state.get("step", 0))


def strict_load_model(model, ckpt: Path, num_train_data: int) -> int:
    """Load a run's model weights strictly (after sizing grids to the saved step); returns the step."""
    model_state, step = load_model_state(ckpt)
    model.update_to_step(step)
    runs.check_tcnn(None, model_state)
    runs.strict_load(model, model_state, num_train_data=num_train_data)
    return step


def load_run(load_config: Path, data: Optional[Path], device: str = "cpu") -> LoadedRun:
    """Any run, rebuilt from its config.yml and loaded strictly (inference mode: cameras, no cached images)."""
    run_cfg, run_dir, ckpt = check_input_config(load_config)
    cfg = copy.deepcopy(run_cfg)
    cfg.pipeline.datamanager = data_override(run_cfg, data)
    pipeline = runs.setup_pipeline(cfg, device, "inference", Path(load_config))
    pipeline.eval()
    step = strict_load_model(pipeline.model, ckpt, len(pipeline.datamanager.train_dataset))
    cfg.pipeline.datamanager = _with_data(run_cfg.pipeline.datamanager, cfg.pipeline.datamanager.data)
    return LoadedRun(cfg, pipeline, run_dir, ckpt, step)


def _with_data(dm_cfg, data: Path):
    """The run's own datamanager config with the resolved data path (what a written run records)."""
    dm = copy.deepcopy(dm_cfg)
    dm.data = Path(data).resolve()
    if getattr(dm, "dataparser", None) is not None and hasattr(dm.dataparser, "data"):
        dm.dataparser.data = Path(data).resolve()
    return dm


def build_recolor_run(load_config: Path, data: Optional[Path], method_name: str, device: str = "cpu"):
    """A recolor pipeline (companion method config) around the run of ``load_config``, inner weights loaded strictly.

    Returns (config, pipeline, run_dir, checkpoint, step). The palette is empty and the hue shift 0 (no edit).
    """
    # deferred: loads every method entry point, this plugin's included
    from nerfstudio.utils.eval_utils import all_methods

    run_cfg, run_dir, ckpt = check_input_config(load_config)
    if method_name not in all_methods:
        raise GStickerError(f"method {method_name} is not registered; reinstall gsticker (pip install -e .)")
    config = copy.deepcopy(all_methods[method_name])
    config.experiment_name = run_cfg.experiment_name
    config.viewer = copy.deepcopy(run_cfg.viewer)
    config.machine = copy.deepcopy(run_cfg.machine)
    dm = data_override(run_cfg, data)
    dm.data = dm.dataparser.data = Path(dm.data).resolve()
    config.pipeline.datamanager = dm
    config.data = dm.data
    inner = copy.deepcopy(run_cfg.pipeline.model)
    config.pipeline.model = RecolorModelConfig(
        inner_model=inner,
        eval_num_rays_per_chunk=getattr(inner, "eval_num_rays_per_chunk", 4096),
        wrapped_run={
            "method": run_cfg.method_name,
            "model": type(inner).__name__,
            "config": str(Path(load_config).resolve()),
            "checkpoint": str(ckpt.resolve()),
            "checkpoint_sha256": file_sha256(ckpt),
        },
    )
    pipeline = runs.setup_pipeline(config, device, "inference", Path(load_config))
    pipeline.eval()
    step = strict_load_model(pipeline.model.inner, ckpt, len(pipeline.datamanager.train_dataset))
    return config, pipeline, run_dir, ckpt, step


# ---------------------------------------------------------------------------------------------- writing


def write_run(
    config,
    model,
    step: int,
    out: Path,
    timestamp: str,
    source_run_dir: Optional[Path] = None,
    extra_files: Optional[Dict[str, Any]] = None,
) -> Path:
    """Write ``config`` + the model's weights as a Nerfstudio run under ``out``; returns the run's config.yml."""
    staged = StagedDir(out)
    try:
        rel = run_location(config, staged.tmp, config.method_name, timestamp).relative_to(staged.tmp)
        config.output_dir = out  # what the config records: the final location
        run_dir = staged.tmp / rel
        ckpt_dir = run_dir / config.relative_model_dir
        ckpt_dir.mkdir(parents=True)
        (run_dir / "config.yml").write_text(yaml.dump(config), "utf8")
        state = {
            "step": int(step),
            "pipeline": {"_model." + k: v.detach().cpu() for k, v in shareable_state(model).items()},
            "optimizers": {},
            "schedulers": {},
            "scalers": {},
        }
        torch.save(state, ckpt_dir / f"step-{int(step):09d}.ckpt")
        if source_run_dir is not None and (source_run_dir / "dataparser_transforms.json").is_file():
            shutil.copy2(source_run_dir / "dataparser_transforms.json", run_dir / "dataparser_transforms.json")
        for name, writer in (extra_files or {}).items():
            writer(run_dir / name)
        staged.commit()
    except BaseException:
        staged.abort()
        raise
    return out / rel / "config.yml"


# ---------------------------------------------------------------------------------------------- images


def training_images(dataset, limit: Optional[int] = None) -> List[Tensor]:
    """The training images as float [H, W, 3|4] (alpha kept when the files have it), at the dataset's scale."""
    n = len(dataset) if limit is None else min(limit, len(dataset))
    return [torch.from_numpy(dataset.get_numpy_image(i)).float() / 255.0 for i in range(n)]


def foreground_pixels(images: Sequence[Tensor]) -> Tensor:
    """Pixels with alpha > 0.5 (all pixels of images without alpha), [N, 3]."""
    px = []
    for im in images:
        if im.shape[-1] == 4:
            px.append(im[..., :3][im[..., 3] > 0.5])
        else:
            px.append(im[..., :3].reshape(-1, 3))
    return torch.cat(px)


def composite_on(img: Tensor, bg: Tensor) -> Tensor:
    if img.shape[-1] == 4:
        return img[..., :3] * img[..., 3:] + bg * (1.0 - img[..., 3:])
    return img[..., :3]


@torch.no_grad()
def render_views(
    model, cameras, indices: Sequence[int], desc: str = "rendering", outputs=("rgb",), progress: bool = True
) -> Dict[str, List[Tensor]]:
    """Render cameras[indices] with the model (any wrapper); {name: [H W C] per view} (rgb clamped to [0, 1])."""
    res: Dict[str, List[Tensor]] = {k: [] for k in outputs}
    it = tqdm(list(indices), desc=desc, leave=False, disable=not progress)
    for i in it:
        out = model.get_outputs_for_camera(cameras[int(i) : int(i) + 1].to(model.device))
        for k in outputs:
            v = out.get(k)
            if v is None and k == "rgb":
                v = out.get("rgb_fine")
            if v is None:
                raise GStickerError(
                    f"the model renders no '{k}' output; it is not a NeRF-style run ns-recolor supports"
                )
            res[k].append((v.clamp(0, 1) if k == "rgb" else v).detach().cpu())
    return res
