"""Right-sized base presets for small (<= 200 px) Blender-format scenes and forward-facing captures.

"Model no more than a scene needs": stock nerfacto (2^19-entry hash grids, 4096 rays) costs ~7 s per
iteration on a 2-core CPU; these presets keep the stock model classes and only shrink their sizes.
Measured numbers: docs/experiments/presets.md (``python -m gsticker_plugin.bench.presets``).
"""

from __future__ import annotations

from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig, RAdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.models.tensorf import TensoRFModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from gsticker_plugin import compat
from gsticker_plugin.small_nerf import SmallNeRFModelConfig

# ns-train imports this entry point before it builds or loads a model: the plugin's host fixes go first
compat.apply()


def default_device_type() -> str:
    """``cuda`` when a CUDA device is present, else ``cpu``: what the presets train on unless
    ``--machine.device-type`` says otherwise."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _small_trainer(
    method_name: str, max_num_iterations: int, model, optimizers, viewer_chunk: int, dataparser=None
) -> TrainerConfig:
    """The trainer every preset shares: Blender data (or ``dataparser``), 1024 training rays, checkpoints every 500
    steps (latest only), an eval image every 1000, no mixed precision (CPU), tensorboard, CUDA when present else
    the CPU."""
    return TrainerConfig(
        method_name=method_name,
        steps_per_eval_batch=500,
        steps_per_eval_image=1000,
        steps_per_eval_all_images=1_000_000,
        steps_per_save=500,
        save_only_latest_checkpoint=True,
        max_num_iterations=max_num_iterations,
        mixed_precision=False,
        pipeline=VanillaPipelineConfig(
            datamanager=VanillaDataManagerConfig(
                dataparser=BlenderDataParserConfig() if dataparser is None else dataparser,
                train_num_rays_per_batch=1024,
                eval_num_rays_per_batch=4096,
            ),
            model=model,
        ),
        optimizers=optimizers,
        viewer=ViewerConfig(num_rays_per_chunk=viewer_chunk),
        vis="tensorboard",
        machine=MachineConfig(device_type=default_device_type()),
    )


def _nerfacto_optimizers() -> dict:
    return {
        "proposal_networks": {
            "optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=200000),
        },
        # The stock 1e-2 saturates the torch-implementation color head on small grids (r = g = b).
        "fields": {
            "optimizer": AdamOptimizerConfig(lr=3e-3, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=200000),
        },
        "camera_opt": {
            "optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=5000),
        },
    }


def _nerfacto_model(**scene) -> NerfactoModelConfig:
    """nerfacto (torch implementation) with the small presets' grids, heads and samples; ``scene``: the rest."""
    return NerfactoModelConfig(
        implementation="torch",
        log2_hashmap_size=15,
        num_levels=8,
        hidden_dim=32,
        hidden_dim_color=64,
        num_nerf_samples_per_ray=32,
        num_proposal_samples_per_ray=(64, 32),
        proposal_net_args_list=[
            {"hidden_dim": 16, "log2_hashmap_size": 14, "num_levels": 5, "max_res": 128, "use_linear": False},
            {"hidden_dim": 16, "log2_hashmap_size": 14, "num_levels": 5, "max_res": 256, "use_linear": False},
        ],
        use_average_appearance_embedding=False,
        camera_optimizer=CameraOptimizerConfig(mode="off"),
        eval_num_rays_per_chunk=1 << 13,
        **scene,
    )


def nerfacto_capture_config(max_num_iterations: int = 2000) -> TrainerConfig:
    """nerfacto (torch implementation) sized for a 100-200 px forward-facing capture in the nerfstudio-data format:
    stock nerfacto's scene contraction, near 0.05 / far 1000, piecewise proposal sampler and ``last_sample``
    background, with the small preset's grids, no camera optimizer (the dataset's poses are the run's) and the
    origin at the cameras' focus (centring on the camera positions puts a forward-facing scene in the contracted
    region: 16.4 dB test PSNR after 3000 steps on the generated capture, 26.8 dB with focus after 600)."""
    return _small_trainer(
        "gsticker-nerfacto-capture",
        max_num_iterations,
        model=_nerfacto_model(
            max_res=512,
            background_color="last_sample",
            near_plane=0.05,
            far_plane=1000.0,
            proposal_initial_sampler="piecewise",
            disable_scene_contraction=False,
        ),
        optimizers=_nerfacto_optimizers(),
        viewer_chunk=1 << 13,
        dataparser=NerfstudioDataParserConfig(center_method="focus"),
    )


def nerfacto_small_config(max_num_iterations: int = 3000) -> TrainerConfig:
    """nerfacto (torch implementation) sized for a 100-200 px object scene, with the Blender recipe."""
    return _small_trainer(
        "gsticker-nerfacto-small",
        max_num_iterations,
        model=_nerfacto_model(
            max_res=256,
            background_color="white",
            near_plane=2.0,
            far_plane=6.0,
            proposal_initial_sampler="uniform",
            disable_scene_contraction=True,
            distortion_loss_mult=0.0,
            average_init_density=0.01,
        ),
        optimizers=_nerfacto_optimizers(),
        viewer_chunk=1 << 13,
    )


def tensorf_small_config(max_num_iterations: int = 2000) -> TrainerConfig:
    """TensoRF (VM) with a 64 -> 160 voxel schedule compressed into 2000 steps, white background."""
    return _small_trainer(
        "gsticker-tensorf-small",
        max_num_iterations,
        model=TensoRFModelConfig(
            init_resolution=64,
            final_resolution=160,
            upsampling_iters=(300, 600, 900, 1200),
            num_samples=128,
            num_uniform_samples=64,
            num_den_components=16,
            num_color_components=48,
            background_color="white",
            regularization="tv",
            camera_optimizer=CameraOptimizerConfig(mode="off"),
            eval_num_rays_per_chunk=1 << 12,
        ),
        optimizers={
            "fields": {
                "optimizer": AdamOptimizerConfig(lr=1e-3),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_num_iterations),
            },
            "encodings": {
                "optimizer": AdamOptimizerConfig(lr=0.02),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=2e-3, max_steps=max_num_iterations),
            },
            "camera_opt": {
                "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-5, max_steps=5000),
            },
        },
        viewer_chunk=1 << 12,
    )


def vanilla_nerf_small_config(max_num_iterations: int = 3000) -> TrainerConfig:
    """vanilla-nerf (stock model and fields, 4 x 64 MLPs, 32 + 32 samples) for a 100 px object scene."""
    return _small_trainer(
        "gsticker-vanilla-nerf-small",
        max_num_iterations,
        model=SmallNeRFModelConfig(
            num_coarse_samples=32,
            num_importance_samples=32,
            background_color="white",
            eval_num_rays_per_chunk=1 << 12,
        ),
        optimizers={
            "fields": {
                "optimizer": RAdamOptimizerConfig(lr=2e-3, eps=1e-8),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=2e-4, max_steps=max_num_iterations),
            },
        },
        viewer_chunk=1 << 12,
    )


nerfacto_small = MethodSpecification(
    config=nerfacto_small_config(),
    description="[gsticker] nerfacto sized for <=200 px object scenes on a CPU (2^15 hash, 8 levels, 1024 rays).",
)
nerfacto_capture = MethodSpecification(
    config=nerfacto_capture_config(),
    description="[gsticker] nerfacto for <=200 px forward-facing captures (nerfstudio-data, contraction) on a CPU.",
)
tensorf_small = MethodSpecification(
    config=tensorf_small_config(),
    description="[gsticker] TensoRF VM sized for <=200 px object scenes on a CPU (64->160 voxels, 2000 steps).",
)
vanilla_nerf_small = MethodSpecification(
    config=vanilla_nerf_small_config(),
    description="[gsticker] vanilla-nerf sized for <=200 px object scenes on a CPU (4 x 64 MLPs, 32 + 32 samples).",
)
