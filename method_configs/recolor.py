"""Companion methods of ``ns-recolor``: ``gsticker-palette`` and ``gsticker-hue``.

Runs of these methods are written by ``ns-recolor palette|hue`` (a config.yml wrapping another run's model plus a
checkpoint); registering them lets stock ``eval_setup``, ``ns-viewer`` and ``ns-render`` open those runs.
``ns-train gsticker-palette`` itself has nothing to train and says so in one line.
"""

from __future__ import annotations

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from gsticker_plugin import compat
from gsticker_plugin.recolor.model import RecolorModelConfig, RecolorTrainerConfig

# ns-train imports this entry point before it builds or loads a model: the plugin's host fixes go first
compat.apply()


def recolor_config(method_name: str) -> RecolorTrainerConfig:
    return RecolorTrainerConfig(
        method_name=method_name,
        max_num_iterations=1,
        steps_per_save=1,
        mixed_precision=False,
        pipeline=VanillaPipelineConfig(datamanager=VanillaDataManagerConfig(), model=RecolorModelConfig()),
        optimizers={},
        viewer=ViewerConfig(num_rays_per_chunk=1 << 13),
        vis="viewer",
    )


gsticker_palette = MethodSpecification(
    config=recolor_config("gsticker-palette"),
    description="[gsticker] A run recolored by palette (made by `ns-recolor palette`; open it with ns-viewer, "
    "palette entries are live color controls).",
)
gsticker_hue = MethodSpecification(
    config=recolor_config("gsticker-hue"),
    description="[gsticker] A run with its colors hue-rotated at the model level (made by `ns-recolor hue`).",
)
