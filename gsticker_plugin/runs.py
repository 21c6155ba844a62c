"""Runs: reading any Nerfstudio run (its config.yml, its latest checkpoint, its data) and loading it strictly.

Nerfstudio's ``Pipeline.load_state_dict`` silently retries with ``strict=False`` when keys do not match;
a watermark stuck onto a half-loaded base would be worthless, so everything here is strict and every
failure is a one-line :class:`GStickerError` naming the fix.
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import importlib.util
import io
import pickle
import re
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import torch
import yaml
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.datamanagers.parallel_datamanager import ParallelDataManager
from nerfstudio.engine.trainer import TrainerConfig

from gsticker_plugin import config_check, hashgrid
from gsticker_plugin.compat import allow_numpy_checkpoint_types
from gsticker_plugin.errors import GStickerError


def resolve_checkpoint(
    load_checkpoint: Optional[Path], load_dir: Optional[Path], load_step: Optional[int]
) -> Optional[Path]:
    """The checkpoint file named by ``--load-checkpoint`` or ``--load-dir`` (+ ``--load-step``), if any."""
    if load_checkpoint is not None:
        p = Path(load_checkpoint)
        if not p.is_file():
            raise GStickerError(
                f"checkpoint {p} does not exist; pass --load-checkpoint RUN/nerfstudio_models/step-N.ckpt"
            )
        return p
    if load_dir is not None:
        d = Path(load_dir)
        ckpts = sorted(d.glob("step-*.ckpt")) if d.is_dir() else []
        if not ckpts:
            raise GStickerError(f"no step-*.ckpt in {d}; pass --load-dir RUN/nerfstudio_models")
        if load_step is not None:
            p = d / f"step-{load_step:09d}.ckpt"
            if not p.is_file():
                raise GStickerError(f"{p} does not exist; pick --load-step from {[c.name for c in ckpts]}")
            return p
        return latest_checkpoint(d)
    return None


def latest_checkpoint(folder: Path) -> Optional[Path]:
    """The ``step-N.ckpt`` of ``folder`` with the largest N (None when there is none): the one rule for "latest"."""
    folder = Path(folder)
    numbered = [
        (int(m.group(1)), c)
        for c in (folder.glob("step-*.ckpt") if folder.is_dir() else [])
        if (m := re.fullmatch(r"step-(\d+)", c.stem))
    ]
    return max(numbered)[1] if numbered else None


def relocate(config, output_dir: Path, experiment_name: str, method_name: str, timestamp: str):
    """Point a run's TrainerConfig at ``output_dir/experiment/method/timestamp`` (Nerfstudio's layout), loading
    nothing: a new run. Returns that folder."""
    config.output_dir = Path(output_dir)
    config.experiment_name = experiment_name
    config.method_name = method_name
    config.timestamp = timestamp
    config.load_dir = config.load_checkpoint = config.load_step = config.load_config = None
    return Path(output_dir) / experiment_name / method_name / timestamp


def run_config_path(checkpoint: Path) -> Path:
    cfg = checkpoint.resolve().parent.parent / "config.yml"
    if not cfg.is_file():
        raise GStickerError(
            f"no config.yml beside {checkpoint} (expected {cfg}); point --load-checkpoint at "
            "RUN/nerfstudio_models/step-N.ckpt inside an intact Nerfstudio run folder"
        )
    return cfg


TRUSTED_PACKAGES = ("nerfstudio", "gsticker_plugin", "method_configs")
PATH_CLASSES = (
    "pathlib.Path",
    "pathlib.PosixPath",
    "pathlib.WindowsPath",
    "pathlib.PurePath",
    "pathlib.PurePosixPath",
    "pathlib.PureWindowsPath",
)


def method_packages() -> Tuple[str, ...]:
    """Top-level packages of Nerfstudio's own methods, gsticker and every installed ``nerfstudio.method_configs``
    entry point: the code a run's config.yml may name."""
    eps = entry_points(group="nerfstudio.method_configs")
    return tuple(sorted(set(TRUSTED_PACKAGES) | {ep.value.split(":")[0].split(".")[0] for ep in eps}))


class RunConfigLoader(yaml.Loader):
    """Reads a Nerfstudio config.yml, building only config dataclasses and names of installed Nerfstudio methods,
    torch optimizers and schedulers, enums and paths; anything else (a suspect's ``os.system``) is refused before
    its module is imported."""

    packages: Tuple[str, ...] = TRUSTED_PACKAGES

    def _trusted(self, suffix: str, node, what: str):
        top = suffix.split(".")[0]
        if not (top in self.packages or suffix in PATH_CLASSES or suffix.startswith("torch.optim.")):
            raise yaml.constructor.ConstructorError(
                None, None, f"{what} {suffix!r} is not a Nerfstudio config class", node.start_mark
            )
        obj = self.find_python_name(suffix, node.start_mark)
        if what == "object" and not (isinstance(obj, type) and dataclasses.is_dataclass(obj)):
            raise yaml.constructor.ConstructorError(
                None, None, f"{suffix!r} is not a config dataclass", node.start_mark
            )
        if what == "call" and not (suffix in PATH_CLASSES or (isinstance(obj, type) and issubclass(obj, enum.Enum))):
            raise yaml.constructor.ConstructorError(
                None, None, f"{suffix!r} may not be called by a config", node.start_mark
            )
        return obj

    def construct_python_name(self, suffix, node):
        self._trusted(suffix, node, "name")
        return super().construct_python_name(suffix, node)

    def construct_python_object(self, suffix, node):
        self._trusted(suffix, node, "object")
        return super().construct_python_object(suffix, node)

    def construct_python_object_apply(self, suffix, node, newobj=False):
        self._trusted(suffix, node, "call")
        return super().construct_python_object_apply(suffix, node, newobj)

    def construct_python_object_new(self, suffix, node):
        self._trusted(suffix, node, "call")
        return super().construct_python_object_new(suffix, node)

    def construct_python_module(self, suffix, node):
        raise yaml.constructor.ConstructorError(None, None, f"module {suffix!r} in a config", node.start_mark)


for _tag, _method in (
    ("name", RunConfigLoader.construct_python_name),
    ("object", RunConfigLoader.construct_python_object),
    ("object/apply", RunConfigLoader.construct_python_object_apply),
    ("object/new", RunConfigLoader.construct_python_object_new),
    ("module", RunConfigLoader.construct_python_module),
):
    RunConfigLoader.add_multi_constructor(f"tag:yaml.org,2002:python/{_tag}:", _method)


def load_run_config(config_path: Path):
    """Parse a run's config.yml with :class:`RunConfigLoader`; a method whose package is missing, or a file that asks
    for anything but config classes, gives a one-line error."""
    loader = type("Loader", (RunConfigLoader,), {"packages": method_packages()})
    try:
        config = yaml.load(Path(config_path).read_text(), Loader=loader)
    except (ModuleNotFoundError, ImportError, AttributeError) as e:
        name = getattr(e, "name", None) or str(e)
        raise GStickerError(
            f"{config_path} was written by a method that is not installed here ({name}); "
            "install that method's package (pip install ...) and retry"
        ) from None
    except yaml.constructor.ConstructorError as e:
        raise GStickerError(
            f"{config_path} is refused: {e.problem} (line {e.problem_mark.line + 1 if e.problem_mark else '?'}); "
            "only config.yml files written by Nerfstudio are read"
        ) from None
    except yaml.YAMLError as e:
        raise GStickerError(
            f"{config_path} is not a readable Nerfstudio config ({type(e).__name__}); restore the run's config.yml"
        ) from None
    except (OSError, UnicodeDecodeError) as e:
        raise GStickerError(f"{config_path} cannot be read ({type(e).__name__}); pass RUN/config.yml") from None
    config_check.check(config, str(config_path))
    return config


def checkpoint_step(checkpoint: Path) -> int:
    """The training step of a Nerfstudio checkpoint (``step-000002999.ckpt`` -> 2999; read from it otherwise)."""
    m = re.fullmatch(r"step-(\d+)", Path(checkpoint).stem)
    return int(m.group(1)) if m else int(load_checkpoint_state(checkpoint).get("step", 0))


def load_checkpoint_state(checkpoint: Path) -> Dict[str, Any]:
    allow_numpy_checkpoint_types()  # numpy 2 scalars in the optimizer state; not only after the plugin's host fixes ran
    try:  # tensors, containers and numpy's scalar types only: a suspect checkpoint is never unpickled
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise GStickerError(
            f"checkpoint {checkpoint} holds Python objects beyond tensors and is refused (a checkpoint is never "
            "unpickled); point at a checkpoint written by Nerfstudio"
        ) from None
    except Exception as e:
        raise GStickerError(
            f"checkpoint {checkpoint} is truncated or corrupt ({type(e).__name__}); "
            "copy it again or point at another step-N.ckpt"
        ) from None
    if not isinstance(state, dict) or "pipeline" not in state:
        raise GStickerError(f"{checkpoint} is not a Nerfstudio checkpoint (no 'pipeline' entry)")
    return state


def model_state_from_pipeline_state(pipeline_state: Dict[str, Any], prefix: str = "_model.") -> Dict[str, Any]:
    out = {}
    for k, v in pipeline_state.items():
        k = k[len("module.") :] if k.startswith("module.") else k
        if k.startswith(prefix):
            out[k[len(prefix) :]] = v
    return out


def check_tcnn(model_config, model_state: Dict[str, Any]) -> None:
    """A tinycudann checkpoint cannot be loaded into the torch implementation (different key layouts)."""
    tcnn_layout = any(k.endswith(".params") for k in model_state)
    if tcnn_layout and importlib.util.find_spec("tinycudann") is None:
        raise GStickerError(
            "the base was trained with tinycudann (tcnn key layout) and tinycudann is not "
            "installed here; install tinycudann (needs CUDA) or retrain the base with "
            "--pipeline.model.implementation torch"
        )


def strict_load(model: torch.nn.Module, model_state: Dict[str, Any], num_train_data: Optional[int] = None) -> None:
    """Load every key, with matching shapes, or stop with a one-line reason."""
    own = model.state_dict()
    missing = [k for k in own if k not in model_state]
    unexpected = [k for k in model_state if k not in own]
    mismatched = [
        (k, tuple(own[k].shape), tuple(model_state[k].shape))
        for k in own
        if k in model_state and hasattr(model_state[k], "shape") and own[k].shape != model_state[k].shape
    ]
    if mismatched:
        k, a, b = mismatched[0]
        if "appearance" in k and num_train_data is not None:
            raise GStickerError(
                f"the data has {a[0]} training images but the base was trained on {b[0]} "
                "(appearance embedding size differs); pass --data with the base's dataset"
            )
        raise GStickerError(
            f"base weight {k} has shape {b} but the rebuilt base expects {a} "
            f"({len(mismatched)} mismatches); rebuild with the run's own config.yml, unmodified"
        )
    if missing or unexpected:
        try:  # a module's load hook may fill what its stored form leaves out (a shared run's folded sticker)
            model.load_state_dict(model_state, strict=True)
            return
        except RuntimeError:
            pass
        raise GStickerError(
            f"base checkpoint does not match its model: {len(missing)} missing keys "
            f"(e.g. {missing[:2]}), {len(unexpected)} unexpected (e.g. {unexpected[:2]}); "
            "use the checkpoint written by the same run as its config.yml"
        )
    model.load_state_dict(model_state, strict=True)


def load_pipeline_strictly(pipeline, state: Dict[str, Any], checkpoint: Path) -> None:
    """Load a checkpoint's pipeline state with every key matching (Nerfstudio's own load silently retries non-strictly:
    a half-loaded suspect would render at chance and read "not shown")."""
    pstate = {(k[len("module.") :] if k.startswith("module.") else k): v for k, v in state["pipeline"].items()}
    pipeline.model.update_to_step(int(state.get("step", 0)))
    try:
        pipeline.load_state_dict(pstate, strict=True)
    except RuntimeError as e:
        lines = [" ".join(x.split()) for x in str(e).splitlines()[1:] if x.strip()]
        detail = "; ".join(lines)[:400] or str(e).splitlines()[0][:200]
        raise GStickerError(
            f"checkpoint {checkpoint} does not match its run's model ({detail}); use the checkpoint "
            "written by the same run as its config.yml"
        ) from None


def resolve_data_path(recorded: Optional[Path], override: Optional[Path]) -> Path:
    if override is not None:
        if not Path(override).exists():
            raise GStickerError(f"--data {override} does not exist; pass the base's dataset folder")
        return Path(override)
    if recorded is None or not Path(recorded).exists():
        raise GStickerError(
            f"the base's dataset {recorded} does not exist from here; pass --data with the "
            "folder that holds the base's training images"
        )
    return Path(recorded)


def base_summary(config) -> Tuple[str, str]:
    model_cfg = config.pipeline.model
    return config.method_name, type(model_cfg).__name__


def final_rgb(outputs: Dict[str, Any]) -> torch.Tensor:
    """The final image of any run's ``get_outputs_for_camera`` (vanilla-nerf names it ``rgb_fine``)."""
    rgb = outputs.get("rgb")
    if rgb is None:
        rgb = outputs.get("rgb_fine")
    if rgb is None:
        raise GStickerError(
            f"the model renders no 'rgb' (or 'rgb_fine') output, only {sorted(outputs)}; "
            "use a NeRF-style run (nerfacto, vanilla-nerf, tensorf)"
        )
    return rgb


def pick_device(choice: str) -> torch.device:
    """``--device auto|cpu|cuda`` as a torch device (auto: CUDA when present)."""
    if choice == "cuda" and not torch.cuda.is_available():
        raise GStickerError("--device cuda but no CUDA device is available; use --device cpu or auto")
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(choice)


def spawns_workers(target) -> bool:
    """Whether a data manager class starts worker processes (nerfacto's ParallelDataManager)."""
    cls = getattr(target, "__origin__", target)
    return isinstance(cls, type) and issubclass(cls, ParallelDataManager)


def load_run(config_path: Path, data: Optional[Path] = None, device: Optional[torch.device] = None):
    """A run rebuilt like nerfstudio's ``eval_setup`` (test mode), with one-line errors instead of exits."""
    config_path = Path(config_path)
    if config_path.is_dir() and (config_path / "config.yml").is_file():
        config_path = config_path / "config.yml"
    if not config_path.is_file():
        raise GStickerError(f"--load-config {config_path} does not exist; pass RUN/config.yml of the suspect run")
    config = load_run_config(config_path)
    # deferred: all_methods imports every installed method's entry point, this plugin's (which imports this module)
    from nerfstudio.configs.method_configs import all_methods

    if not isinstance(config, TrainerConfig):
        raise GStickerError(f"{config_path} is not a Nerfstudio run config; pass RUN/config.yml")
    if config.method_name not in all_methods:
        raise GStickerError(
            f"{config_path} was written by method {config.method_name!r}, which is not installed "
            "here; install its package and retry"
        )
    config.pipeline.datamanager._target = all_methods[config.method_name].pipeline.datamanager._target
    # checkpoint: beside the config only (the run folder judged, wherever it was moved); a suspect config's own
    # output_dir could point anywhere on this disk
    ckpt = latest_checkpoint(config_path.parent / "nerfstudio_models")
    if ckpt is None:
        raise GStickerError(
            f"the run {config_path.parent} has no checkpoint (no step-*.ckpt in "
            f"{config_path.parent / 'nerfstudio_models'}); copy its nerfstudio_models folder beside its config.yml"
        )
    dm = config.pipeline.datamanager
    recorded = getattr(dm, "data", None) or getattr(dm.dataparser, "data", None)
    if data is not None:
        if not Path(data).exists():
            raise GStickerError(f"--data {data} does not exist; pass the run's dataset folder")
        dm.data = Path(data)
        if hasattr(dm.dataparser, "data"):
            dm.dataparser.data = Path(data)
    elif recorded is None or not Path(recorded).exists():
        raise GStickerError(
            f"the run's dataset {recorded} does not exist from here (its cameras are needed); "
            "pass --data with the run's dataset folder"
        )
    if spawns_workers(config.pipeline.datamanager._target):
        # nerfacto's ParallelDataManager spawns a worker process that samples training rays nobody reads here, and
        # its __del__ printed a traceback at exit: the same dataparser in nerfstudio's in-process data manager
        config.pipeline.datamanager = copy_datamanager(config, None)
    device = device or torch.device("cuda" if torch.cuda.is_available() else "cpu")
    pipeline = setup_pipeline(config, device, "test", config_path)
    pipeline.eval()
    state = load_checkpoint_state(ckpt)
    load_pipeline_strictly(pipeline, state, ckpt)
    pipeline.eval()
    hashgrid.speed_up(pipeline.model)
    return config, pipeline, ckpt


def load_run_at(config_path: Path, checkpoint: Path, data: Optional[Path] = None, device=None):
    """:func:`load_run`, then the weights of ``checkpoint`` (one of the run's, e.g. an earlier step than its latest)
    loaded strictly when they are not the ones it loaded. Returns (config, pipeline, checkpoint state)."""
    config, pipeline, loaded = load_run(config_path, data=data, device=device)
    state = load_checkpoint_state(checkpoint)
    if Path(loaded).resolve() != Path(checkpoint).resolve():
        ds = pipeline.datamanager.train_dataset
        strict_load(pipeline.model, model_state_from_pipeline_state(state["pipeline"]), len(ds))
    return config, pipeline, state


def setup_pipeline(config, device, test_mode: str, source: Path):
    """``config.pipeline.setup`` for a run read from ``source``, with no one to answer a prompt: a dataparser that asks
    (COLMAP's "downscale the images now?") reads "no" and its exit becomes a one-line error, as does a dataset that
    cannot be read."""
    old_stdin = sys.stdin
    sys.stdin = io.StringIO("n\n" * 8)
    try:
        return config.pipeline.setup(device=device, test_mode=test_mode)
    except GStickerError:
        raise
    except SystemExit:
        raise GStickerError(
            f"the dataparser of {source} stopped while reading its dataset (it asked a question, e.g. to downscale "
            "images, and was told no); prepare the dataset with nerfstudio first, or pass --data"
        ) from None
    except (FileNotFoundError, OSError) as e:
        raise GStickerError(
            f"could not load the dataset of {source} ({type(e).__name__}: {e}); pass --data with the run's dataset folder"
        ) from None
    finally:
        sys.stdin = old_stdin


def copy_datamanager(base_config, data_override: Optional[Path]) -> VanillaDataManagerConfig:
    """The base's dataparser and data path in a single-process VanillaDataManager (we sample no ray batches)."""
    dm = base_config.pipeline.datamanager
    dataparser = copy.deepcopy(dm.dataparser)
    recorded = dm.data if getattr(dm, "data", None) is not None else getattr(dataparser, "data", None)
    data = resolve_data_path(recorded, data_override)
    dataparser.data = data
    return VanillaDataManagerConfig(
        dataparser=dataparser,
        data=data,
        train_num_rays_per_batch=1024,
        eval_num_rays_per_batch=1024,
        camera_res_scale_factor=dm.camera_res_scale_factor,
    )
