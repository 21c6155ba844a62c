"""``python open_without_gsticker.py RUN/config.yml``: open a run with Nerfstudio's own ``eval_setup`` while neither
``gsticker_plugin`` nor ``method_configs`` can be imported (as on a recipient's machine without gsticker), render its
first test camera and print one JSON line: method, model class, render shape, gsticker modules loaded."""

import importlib.abc
import importlib.metadata as metadata
import json
import sys
from pathlib import Path

BLOCKED = ("gsticker_plugin", "method_configs")


class Blocked(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{name} is not installed here")
        return None


_entry_points = metadata.entry_points


def entry_points(**selection):
    """Installed entry points without gsticker's (its method registrations)."""
    found = _entry_points(**selection)
    if not selection:
        return found
    return metadata.EntryPoints(e for e in found if e.value.split(":")[0].split(".")[0] not in BLOCKED)


def main() -> None:
    sys.meta_path.insert(0, Blocked())
    metadata.entry_points = entry_points
    import torch
    import torchmetrics.image.lpip as lpip
    from nerfstudio.utils.eval_utils import eval_setup

    # offline machine: stock nerfacto downloads LPIPS weights when it is built (a metric, not used to render)
    lpip.LearnedPerceptualImagePatchSimilarity = lambda **kwargs: torch.nn.Identity()
    config, pipeline, _, _ = eval_setup(Path(sys.argv[1]), test_mode="test")
    cameras = pipeline.datamanager.eval_dataset.cameras
    with torch.no_grad():
        out = pipeline.model.get_outputs_for_camera(cameras[0:1].to(pipeline.device))
    print(
        json.dumps(
            {
                "method": config.method_name,
                "model": type(pipeline.model).__name__,
                "rgb": list(out["rgb"].shape),
                "gsticker_loaded": sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED),
            }
        )
    )


if __name__ == "__main__":
    main()
