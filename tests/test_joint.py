"""Tests for the joint-training benchmark's packed pool (gsticker_plugin/bench/joint.py), on a tiny cached view."""

from __future__ import annotations

import json

import torch
from conftest import tiny_view_and_wrap

from gsticker_plugin.bench.joint import Train, pack_view, psnr_budget, render_packed, train
from gsticker_plugin.fastpath import with_density_change


def _gate(wrap):
    return wrap.sticker, (wrap.gate.mu, wrap.gate.beta, wrap.gate.scale, wrap.gate_threshold)


def ray_view():
    """The tiny view with its samples on straight rays (samples tile each ray, as Nerfstudio's do), some of them
    leaving the sticker's box."""
    view, wrap, bg = tiny_view_and_wrap()
    g = torch.Generator().manual_seed(1)
    n, s = view.density.shape[:2]
    origins = torch.rand(n, 1, 3, generator=g) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(n, 1, 3, generator=g), dim=-1)
    view.deltas = 0.05 + 0.2 * torch.rand(n, s, 1, generator=g)
    mids = torch.cumsum(view.deltas, dim=1) - view.deltas / 2
    view.positions = (origins + dirs * mids).half()
    return view, wrap, bg


def test_packed_view_renders_what_the_fast_path_renders():
    view, wrap, bg = ray_view()
    packed = pack_view(view, wrap)
    for seed in range(3):
        msg = torch.randint(0, 2, (6,), generator=torch.Generator().manual_seed(seed))
        delta, _ = wrap.delta(view.density, view.positions.float(), msg)
        exact = with_density_change(view, delta, bg)
        mine = render_packed(packed, wrap.aabb, *_gate(wrap), bg, msg)
        assert not torch.allclose(exact, view.image, atol=1e-3)  # the message moves the render
        assert float((mine - exact).abs().max().detach()) < 2e-3


def test_packing_drops_rays_without_an_open_gate():
    view, wrap, _ = ray_view()
    view.density[:5] = 0.0  # these rays see nothing: the gate stays shut
    packed = pack_view(view, wrap)
    assert set(packed["rays"].tolist()).isdisjoint(range(5))


def test_psnr_budget_is_loose_then_ramps_to_tight():
    cfg = Train(loose_psnr=25.0, tight_psnr=35.0, loose_share=0.3)
    assert psnr_budget(cfg, 0.0) == psnr_budget(cfg, 0.3) == 25.0
    assert psnr_budget(cfg, 0.45) == 30.0
    assert psnr_budget(cfg, 0.6) == psnr_budget(cfg, 1.0) == 35.0


def test_train_reads_an_owner_message_drawn_after_training_and_writes_the_page_from_its_json(tmp_path):
    view, wrap, bg = ray_view()
    packed = pack_view(view, wrap)
    data = {
        "version": 1,
        "views": {"train": [packed, packed], "heldout": [packed]},
        "gate": {
            "mu": float(wrap.gate.mu),
            "beta": float(wrap.gate.beta),
            "scale": float(wrap.gate.scale),
            "threshold": wrap.gate_threshold,
        },
        "background": bg,
        "aabb": wrap.aabb,
        "num_bits": 6,
        "sticker": {"num_frequencies": 2, "hidden_dim": 8},
        "source": {"checkpoint": "tiny", "train_cameras": "training", "max_abs_error": 0.0},
    }
    torch.save(data, tmp_path / "pool.pt")
    cfg = Train(
        pool=tmp_path / "pool.pt",
        backbones=("small",),
        max_steps=3,
        views_per_step=2,
        messages_per_view=2,
        eval_every=0.0,
        output_dir=tmp_path,
        doc=tmp_path / "page.md",
    )
    res = train(cfg)
    run = res["runs"][0]
    assert run["steps"] == 3 and run["images"] == 12 and len(run["curve"]) == 4  # an evaluation before every step
    assert json.loads((tmp_path / "page.json").read_text())["runs"][0]["steps"] == 3
    page = (tmp_path / "page.md").read_text()
    oh = run["owner_heldout"]
    assert f"bit accuracy {oh['bit_acc']:.3f}" in page and f"max {oh['clean_max_matches']}" in page
    assert len((tmp_path / "curve-small.jsonl").read_text().splitlines()) == 4


def test_training_side_imports_without_nerfstudio():
    """The GPU machine that runs ``train`` has PyTorch but no Nerfstudio."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['nerfstudio'] = None; import gsticker_plugin.bench.joint as j; print(j.PACK_VERSION)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "1", out.stderr[-2000:]
