"""``ns-train geometrysticker --load-checkpoint BASE_RUN/nerfstudio_models/step-N.ckpt``."""

from __future__ import annotations

from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from gsticker_plugin import compat
from gsticker_plugin.model import GeometryStickerModelConfig
from gsticker_plugin.pipeline import GeometryStickerPipelineConfig
from gsticker_plugin.trainer import GeometryStickerTrainerConfig
from method_configs.presets import default_device_type

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
        machine=MachineConfig(device_type=default_device_type()),
    )


def geometrysticker_robust_config() -> GeometryStickerTrainerConfig:
    """The images-alone operating point: a mark near 36 dB whose bits stay separable in the image under noise, JPEG and
    blur (sticker bound 30, scale-free conditioning on the sharp and the 1 px blurred change, weight 3), on the pool
    sizes, warm-up and learning-rate decay (to its floor at step 1500) it was measured with (docs/verify.md)."""
    cfg = geometrysticker_config()
    cfg.method_name = "geometrysticker-robust"
    cfg.max_num_iterations = 2000
    cfg.steps_per_save = 500
    p = cfg.pipeline
    p.model.sticker_amplitude = 30.0
    p.mark_psnr, p.target_psnr = 36.0, 35.0
    p.condition_weight, p.condition_scale_free, p.condition_blur = 3.0, True, 1.0
    p.pool_train_views, p.pool_novel_views, p.monitor_views = 16, 16, 4
    p.warmup_steps, p.steps_per_monitor = 50, 50
    return cfg


geometrysticker = MethodSpecification(
    config=geometrysticker_config(),
    description="[gsticker] Stick a 48-bit owner message onto a trained model's geometry "
    "(--load-checkpoint BASE_RUN/nerfstudio_models/step-N.ckpt); writes a shareable model and a secret owner key.",
)
geometrysticker_robust = MethodSpecification(
    config=geometrysticker_robust_config(),
    description="[gsticker] geometrysticker for owners who must read images alone: a ~36 dB mark whose bits survive "
    "noise, JPEG and blur (conditioned sticker, 2000 steps).",
)
