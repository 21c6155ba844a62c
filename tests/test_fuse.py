"""The fused export's pure parts (small tensors); the distillation itself is measured by gsticker_plugin.bench.fuse."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import torch

from gsticker_plugin import fuse
from gsticker_plugin.sticker import composite, render_weights


def _rays(r=5, s=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    density = torch.rand(r, s, 1, generator=g) * 5
    deltas = torch.rand(r, s, 1, generator=g) * 0.2 + 0.01
    rgb = torch.rand(r, s, 3, generator=g)
    steps = torch.cumsum(deltas, dim=-2) + 2.0
    return density, deltas, rgb, steps


def test_transmittance_matches_weights():
    density, deltas, _, _ = _rays()
    t = fuse.transmittance(density, deltas)
    alpha = 1 - torch.exp(-density * deltas)
    assert torch.allclose(t * alpha, render_weights(density, deltas), atol=1e-6)
    assert torch.allclose(t[:, 0], torch.ones_like(t[:, 0]))


def test_losses_zero_at_teacher_and_positive_elsewhere():
    density, deltas, rgb, steps = _rays()
    bg = torch.ones(3)
    w = fuse.LossWeights()
    same = fuse.distill_losses(density, rgb, density, rgb, deltas, steps, bg, 3.0, 1e-3, w)
    assert all(float(v) == 0.0 for v in same.values())
    other = fuse.distill_losses(density * 0.5, rgb, density, rgb, deltas, steps, bg, 3.0, 1e-3, w)
    for k in ("weights", "accumulation", "depth", "rgb", "log_density", "total"):
        assert float(other[k]) > 0, k


def test_rgb_term_is_the_composite_error():
    density, deltas, rgb, steps = _rays()
    bg = torch.ones(3)
    s_density = density * 1.3
    s_rgb = rgb.flip(-1)
    terms = fuse.distill_losses(s_density, s_rgb, density, rgb, deltas, steps, bg, 1.0, 1e-3, fuse.LossWeights())
    a, _ = composite(s_density, s_rgb, deltas, bg)
    b, _ = composite(density, rgb, deltas, bg)
    assert torch.allclose(terms["rgb"], ((a - b) ** 2).mean(), atol=1e-7)


def test_losses_give_gradients_to_the_student_only():
    density, deltas, rgb, steps = _rays()
    s_density = (density * 0.7).requires_grad_(True)
    s_rgb = rgb.clone().requires_grad_(True)
    t_density = density.clone().requires_grad_(True)
    terms = fuse.distill_losses(
        s_density, s_rgb, t_density, rgb, deltas, steps, torch.ones(3), 3.0, 1e-3, fuse.LossWeights()
    )
    terms["total"].backward()
    assert s_density.grad is not None and float(s_density.grad.abs().sum()) > 0
    assert s_rgb.grad is not None
    assert t_density.grad is None  # the teacher's side is a constant


def test_log_density_floor_keeps_zero_targets_finite():
    density, deltas, rgb, steps = _rays()
    target = density.clone()
    target[:, 2] = 0.0  # the sticker removed density there (relu)
    terms = fuse.distill_losses(density, rgb, target, rgb, deltas, steps, torch.ones(3), 3.0, 1e-2, fuse.LossWeights())
    assert torch.isfinite(terms["total"])


def test_visible_samples():
    deltas = torch.full((1, 4, 1), 1.0)
    opaque_first = torch.tensor([[[0.0], [100.0], [1.0], [1.0]]])
    clear = torch.zeros(1, 4, 1)
    vis = fuse.visible_samples(opaque_first, opaque_first, deltas, 1e-4)
    assert vis.tolist() == [[True, True, False, False]]
    # the base sees through (the sticker removed a surface in the teacher, or the other way around): all visible
    assert fuse.visible_samples(opaque_first, clear, deltas, 1e-4).all()


def test_select_rays():
    changed = torch.tensor([True, False, False, False, False, False, False, False, False, False])
    acc = torch.tensor([0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    g = torch.Generator().manual_seed(0)
    keep = fuse.select_rays(changed, acc, 0.25, g)
    assert keep[:2].tolist() == [0, 1] or {0, 1} <= set(keep.tolist())
    assert len(keep) == 2 + 2  # 25 % of the 8 others
    assert keep.tolist() == sorted(keep.tolist())
    assert len(fuse.select_rays(changed, acc, 0.0, g)) == 2


def test_psnr():
    a = torch.zeros(4, 4, 3)
    assert fuse.psnr(a, a) == float("inf")
    assert abs(fuse.psnr(a, a + 0.1) - 20.0) < 1e-4


def test_sample_pool_take_and_cat():
    r, s = 6, 4
    pool = fuse.SamplePool(
        origins=torch.rand(r, 3),
        directions=torch.rand(r, 3),
        pixel_area=torch.rand(r, 1),
        starts=torch.rand(r, s),
        ends=torch.rand(r, s),
        density=torch.rand(r, s),
        base_density=torch.rand(r, s),
        rgb=torch.rand(r, s, 3).half(),
        changed=torch.rand(r) > 0.5,
    )
    both = fuse.SamplePool.cat([pool, pool.take(torch.tensor([1, 3]))])
    assert len(both) == 8
    assert torch.equal(both.starts[6], pool.starts[1])
    assert both.nbytes() > pool.nbytes()
    rs = fuse.ray_samples_of(pool, torch.device("cpu"))
    assert tuple(rs.shape) == (r, s)
    assert torch.allclose(rs.deltas[..., 0], pool.ends - pool.starts)
    # the samples' positions are the captured rays' (origin + direction * mid-point)
    mid = 0.5 * (pool.starts + pool.ends)
    assert torch.allclose(
        rs.frustums.get_positions(), pool.origins[:, None] + pool.directions[:, None] * mid[..., None]
    )


def test_fused_run_config_and_checkpoint_state(tmp_path):
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
    from nerfstudio.engine.trainer import TrainerConfig
    from nerfstudio.models.nerfacto import NerfactoModelConfig
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    base = TrainerConfig(
        method_name="nerfacto",
        pipeline=VanillaPipelineConfig(
            datamanager=VanillaDataManagerConfig(dataparser=BlenderDataParserConfig()), model=NerfactoModelConfig()
        ),
    )
    base.load_dir = Path("somewhere")
    cfg = fuse.fused_run_config(base, tmp_path, "exp", "ts", data=tmp_path / "data")
    assert cfg.method_name == "nerfacto"
    assert cfg.get_base_dir() == tmp_path / "exp" / "nerfacto" / "ts"
    assert cfg.load_dir is None and base.load_dir == Path("somewhere")  # a copy, the base config untouched
    assert cfg.pipeline.datamanager.data == tmp_path / "data"
    state = fuse.checkpoint_state(
        2999,
        {"_model.field.x": torch.ones(2, requires_grad=True)},
        {"optimizers": {"fields": {}}, "schedulers": {}, "scalers": {}},
    )
    assert set(state) == {"step", "pipeline", "optimizers", "schedulers", "scalers"}
    assert state["step"] == 2999 and not state["pipeline"]["_model.field.x"].requires_grad


def test_pool_cameras_spread_and_seeded():
    from nerfstudio.cameras.cameras import Cameras

    n = 10
    c2w = torch.eye(4)[:3].expand(n, 3, 4).clone()
    c2w[:, 0, 3] = torch.arange(n).float() + 1.0
    cams = Cameras(camera_to_worlds=c2w, fx=10.0, fy=10.0, cx=4.0, cy=4.0, width=8, height=8)
    pipe = SimpleNamespace(datamanager=SimpleNamespace(train_dataset=SimpleNamespace(cameras=cams)))
    a = fuse.pool_cameras(pipe, 4, 3, seed=5)
    b = fuse.pool_cameras(pipe, 4, 3, seed=5)
    assert [n for n, _ in a] == [
        "train/000",
        "train/003",
        "train/006",
        "train/009",
        "orbit/000",
        "orbit/001",
        "orbit/002",
    ]
    assert all(torch.equal(x.camera_to_worlds, y.camera_to_worlds) for (_, x), (_, y) in zip(a, b))
