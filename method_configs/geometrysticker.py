"""``ns-train geometrysticker --load-checkpoint BASE_RUN/nerfstudio_models/step-N.ckpt``."""

from __future__ import annotations

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from gsticker_plugin import compat
from gsticker_plugin.model import GeometryStickerModelConfig
from gsticker_plugin.pipeline import GeometryStickerPipelineConfig
from gsticker_plugin.trainer import GeometryStickerTrainerConfig

# ns-train imports this entry point before it builds or loads a model: the plugin's host fixes go first
compat.apply()


def geometrysticker_config(max_num_iterations: int = 1500) -> GeometryStickerTrainerConfig:
    return GeometryStickerTrainerConfig(
        method_name="geometrysticker",
        max_num_iterations=max_num_iterations,
        steps_per_save=250,
        save_only_latest_checkpoint=True,
        steps_per_eval_batch=1_000_000,
        steps_per_eval_image=1_000_000,
        steps_per_eval_all_images=1_000_000,
        mixed_precision=False,
        # the sticker marks only the final rendering pass: every base draws its own samples (exact fast path and
        # geometric decoding for TensoRF and vanilla-nerf too)
        pipeline=GeometryStickerPipelineConfig(model=GeometryStickerModelConfig(mark_sampling_passes=False)),
        optimizers={
            "sticker": {
                "optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=2e-4, max_steps=max_num_iterations),
            },
            "heads": {
                "optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_num_iterations),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 13),
        vis="tensorboard",
    )


geometrysticker = MethodSpecification(
    config=geometrysticker_config(),
    description="[gsticker] Stick a 48-bit owner message onto a trained model's geometry "
    "(--load-checkpoint BASE_RUN/nerfstudio_models/step-N.ckpt); writes a shareable model and a secret owner key.",
)
