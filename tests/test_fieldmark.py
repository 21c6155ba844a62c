"""The field mark (gsticker_plugin.fieldmark): per-bit patterns in a nerfacto field's own hash table."""

from __future__ import annotations

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.mlp import MLP
from torch import nn

from gsticker_plugin import fieldmark as FM
from gsticker_plugin import hashgrid
from gsticker_plugin.decoders.fieldmark import decode_view
from gsticker_plugin.errors import GStickerError


def tiny_field():
    torch.manual_seed(0)
    enc = HashEncoding(num_levels=4, min_res=4, max_res=32, log2_hashmap_size=8, implementation="torch")
    with torch.no_grad():
        enc.hash_table.normal_(0, 0.1)
    mlp = MLP(in_dim=enc.get_out_dim(), num_layers=2, layer_width=16, out_dim=4, implementation="torch")
    return nn.Module(), enc, mlp


def test_patterns_live_on_their_levels_and_follow_the_seed_alone():
    _, enc, _ = tiny_field()
    size = enc.hash_table_size
    p = FM.patterns(enc.hash_table.shape, size, [1, 2], 48, seed=7)
    assert p.shape == (48, *enc.hash_table.shape)
    assert p[:, :size].abs().sum() == 0 and p[:, 3 * size :].abs().sum() == 0 and p[:, size : 3 * size].std() > 0.9
    assert torch.equal(p, FM.patterns(enc.hash_table.shape, size, [1, 2], 48, seed=7))
    assert not torch.equal(p, FM.patterns(enc.hash_table.shape, size, [1, 2], 48, seed=8))
    with pytest.raises(ValueError, match="outside"):
        FM.patterns(enc.hash_table.shape, size, [4], 48, seed=7)


def test_the_marked_table_is_the_base_table_plus_the_signed_patterns():
    _, enc, _ = tiny_field()
    t = enc.hash_table.data
    p = FM.patterns(t.shape, enc.hash_table_size, [0], 8, seed=1)
    assert torch.equal(FM.marked_table(t, p, torch.zeros(8), 0.3), t)
    s = FM.signs_of(torch.tensor([1, 0, 1, 1, 0, 0, 1, 0]))
    got = FM.marked_table(t, p, s, 0.3)
    assert torch.allclose(got, t + 0.3 * sum(si * pi for si, pi in zip(s, p)) / 8**0.5, atol=1e-6)


def test_sample_features_are_the_first_order_change_of_the_density_logit():
    _, enc, mlp = tiny_field()
    k = 6
    p = FM.patterns(enc.hash_table.shape, enc.hash_table_size, [0, 1, 2, 3], k, seed=3)
    x = torch.rand(200, 3)
    feats = FM.sample_features(enc, mlp, x, p)
    base = enc.hash_table.data.clone()
    assert torch.equal(enc.hash_table.data, base)  # restored
    s = torch.randn(k).clamp(-1, 1)
    eps = 1e-3
    with torch.no_grad():
        pre0 = mlp(enc(x))[..., 0]
        enc.hash_table.data = FM.marked_table(base, p, s, eps)
        pre1 = mlp(enc(x))[..., 0]
        enc.hash_table.data = base
    assert torch.allclose((pre1 - pre0) / eps, feats @ s, atol=2e-3, rtol=1e-2)


def stacked_features(enc, mlp, x, pats):
    """``g . enc(x; P_k) / sqrt(K)`` by encoding each pattern as the encoder's own table (the definition)."""
    k = pats.shape[0]
    e = enc(x).detach().requires_grad_(True)
    (g,) = torch.autograd.grad(mlp(e)[..., 0].sum(), e)
    saved, out = enc.hash_table.data, []
    try:
        for pk in pats:
            enc.hash_table.data = pk
            with torch.no_grad():
                out.append((enc(x) * g).sum(-1))
    finally:
        enc.hash_table.data = saved
    return torch.stack(out, -1) / k**0.5


def test_sample_features_equal_the_encoding_of_each_pattern_also_on_grid_corners_and_chunk_edges():
    """The sparse product over the 8 corners of each level is the encoder's own interpolation of each pattern,
    also where a position lies on the grid (ceiling and floor the same row) and across chunks."""
    _, enc, mlp = tiny_field()
    p = FM.patterns(enc.hash_table.shape, enc.hash_table_size, [0, 1, 2, 3], 10, seed=5)
    x = torch.cat([torch.rand(150, 3), torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.25, 0.75], [1.0, 1.0, 1.0]])])
    got = FM.sample_features(enc, mlp, x, p, chunk=64)
    assert torch.allclose(got, stacked_features(enc, mlp, x, p), atol=1e-6)
    rows, w = hashgrid.corners(enc, x)
    assert rows.shape == w.shape == (len(x), 4, 8) and torch.allclose(w.sum(-1), torch.ones(len(x), 4))
    assert rows.max() < enc.hash_table.shape[0]


def test_a_field_without_a_torch_hash_encoder_is_refused():
    with pytest.raises(GStickerError, match="implementation torch"):
        FM.parts(nn.Linear(2, 2))


def random_view(rays=30, samples=12, k=8):
    g = torch.Generator().manual_seed(4)
    return FM.FieldView(
        rays=torch.arange(rays),
        density=torch.rand(rays, samples, 1, generator=g) * 3,
        deltas=torch.full((rays, samples, 1), 0.1),
        steps=torch.linspace(2, 4, samples).expand(rays, samples)[..., None].contiguous(),
        features=torch.randn(rays, samples, k, generator=g),
        base_signal=torch.zeros(2, rays),
        depth_scale=2.0,
    )


def test_the_closed_form_jacobian_is_forward_mode_autodiff_of_the_prediction():
    from gsticker_plugin.decoders.fit import jacobian

    view = random_view()
    s = torch.rand(8, generator=torch.Generator().manual_seed(5)) * 2 - 1
    got = FM.predict_jacobian(view, s, 0.3)
    want = jacobian(lambda x: FM.predict(view, x, 0.3), s)
    assert got.shape == (60, 8)
    assert torch.allclose(got, want, atol=1e-5, rtol=1e-4)


def test_a_view_marked_with_a_message_decodes_to_it_and_an_unmarked_one_to_nothing():
    from gsticker_plugin.decoders.fit import UNDETERMINED, tie_generator

    view = random_view(rays=200, k=8)
    msg = torch.tensor([1, 0, 0, 1, 1, 0, 1, 0])
    marked = FM.predict(view, FM.signs_of(msg), 0.05).reshape(2, -1)
    outputs = {"accumulation": marked[0], "expected_depth": marked[1] * view.depth_scale / marked[0]}
    view.base_signal = FM.predict(view, torch.zeros(8), 0.05).reshape(2, -1) * torch.tensor([[1.0], [2.0]])
    bits, fit = decode_view(view, outputs, 0.05, tie_generator(0))
    assert torch.equal(bits, msg) and fit.explained > 0.999
    base = view.base_signal
    same = {"accumulation": base[0], "expected_depth": base[1] / base[0]}
    bits, fit = decode_view(view, same, 0.05, tie_generator(0))
    assert (bits == UNDETERMINED).all()


def test_only_rows_training_moved_carry_the_patterns():
    table = torch.tensor([[5e-4, -9e-4], [0.2, 0.0], [1e-4, -0.3], [0.0, 0.0]])
    assert FM.trained_rows(table, 1e-3).tolist() == [False, True, True, False]
    pats = FM.on_rows(torch.ones(3, 4, 2), FM.trained_rows(table, 1e-3))
    assert pats[:, [0, 3]].abs().sum() == 0 and torch.equal(pats[:, [1, 2]], torch.ones(3, 2, 2))


def tiny_nerfacto(monkeypatch):
    """A randomly initialised nerfacto (torch implementation, 4 hash levels) with density everywhere in its box."""
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.models.nerfacto import NerfactoModelConfig

    from gsticker_plugin import compat

    monkeypatch.setenv("GSTICKER_NO_DOWNLOAD", "1")
    compat.apply()
    torch.manual_seed(0)
    proposal = {"hidden_dim": 8, "log2_hashmap_size": 8, "num_levels": 2, "max_res": 16, "use_linear": False}
    cfg = NerfactoModelConfig(
        implementation="torch",
        hidden_dim=16,
        hidden_dim_color=16,
        num_levels=4,
        max_res=32,
        log2_hashmap_size=10,
        num_nerf_samples_per_ray=8,
        num_proposal_samples_per_ray=(16, 8),
        proposal_net_args_list=[proposal, proposal],
        background_color="white",
        disable_scene_contraction=True,
        appearance_embed_dim=4,
    )
    model = cfg.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=2, metadata={})
    model.eval()
    with torch.no_grad():
        FM.parts(model.field)[0].hash_table.normal_(0, 1.0)
    return model


def test_the_image_jacobian_is_the_colour_change_of_the_marked_render(monkeypatch):
    """``a J s`` from :func:`FM.image_view` against the stock render with the marked table, minus the base's: equal to
    first order (density and the colour head's geometry features both change with the table)."""
    from nerfstudio.cameras.cameras import Cameras

    model = tiny_nerfacto(monkeypatch)
    enc, _ = FM.parts(model.field)
    c2w = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2.5]]])
    cam = Cameras(camera_to_worlds=c2w, fx=10.0, fy=10.0, cx=6.0, cy=6.0, width=12, height=12)
    pats = FM.patterns(enc.hash_table.shape, enc.hash_table_size, [0, 1], 8, seed=3)
    view = FM.image_view(model, cam, pats)
    assert view.rays.numel() == 144 and view.jacobian.shape == (144, 3, 8)
    x = torch.rand(50, 3)
    by_row = pats.permute(1, 2, 0).reshape(-1, 8)
    stacked = []
    for pk in pats:  # the encoder with each pattern as its table: what pattern_encodings computes in one product
        saved, enc.hash_table.data = enc.hash_table.data, pk
        with torch.no_grad():
            stacked.append(enc(x).reshape(50, -1, 2))
        enc.hash_table.data = saved
    assert torch.allclose(FM.pattern_encodings(enc, x, by_row, 2), torch.stack(stacked, 2), atol=1e-6)
    signs, a = torch.tensor([1.0, -1, 1, 1, -1, -1, 1, -1]), 1e-3
    with torch.no_grad():
        base = model.get_outputs_for_camera(cam)["rgb"].reshape(-1, 3)
        table = enc.hash_table.data.clone()
        enc.hash_table.data = FM.marked_table(table, pats, signs, a)
        marked = model.get_outputs_for_camera(cam)["rgb"].reshape(-1, 3)
        enc.hash_table.data = table
    change = (marked - base)[view.rays]
    predicted = a * torch.einsum("rck,k->rc", view.jacobian, signs)
    assert torch.allclose(view.base_rgb, base[view.rays])
    assert float((change - predicted).norm() / change.norm()) < 0.02
    assert float((change + predicted).norm() / change.norm()) > 1.9  # the sign matters: not a loose tolerance


def marked_scene(monkeypatch, message, side: int = 24, recolour=None):
    """The tiny nerfacto, a camera ``side`` px square looking at it, 8 patterns, the key and reference the image
    decoder takes, and the base's and the marked field's renders there (``recolour``: a per-sample colour change
    applied to the marked render, as ``ns-recolor`` edits a run)."""
    from types import SimpleNamespace

    from nerfstudio.cameras.cameras import Cameras

    from gsticker_plugin.recolor.model import ColorWrap

    model = tiny_nerfacto(monkeypatch)
    enc, _ = FM.parts(model.field)
    c2w = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2.5]]])
    f, c = 20.0 * side / 24, side / 2
    cam = Cameras(camera_to_worlds=c2w, fx=f, fy=f, cx=c, cy=c, width=side, height=side)
    pats = FM.patterns(enc.hash_table.shape, enc.hash_table_size, [0, 1], 8, seed=3)
    key = SimpleNamespace(message=message, num_bits=8)
    ref = SimpleNamespace(model=model, patterns=pats, amplitude=0.3)
    with torch.no_grad():
        base = model.get_outputs_for_camera(cam)["rgb"]
        table = enc.hash_table.data.clone()
        enc.hash_table.data = FM.marked_table(table, pats, FM.signs_of(message), 0.3)
        wrap = ColorWrap(model.field, recolour) if recolour is not None else None
        marked = model.get_outputs_for_camera(cam)["rgb"]
        if wrap is not None:
            wrap.remove()
        enc.hash_table.data = table
    return SimpleNamespace(model=model, cam=cam, key=key, ref=ref, base=base, marked=marked)


def test_a_picture_of_the_marked_field_at_its_camera_decodes_to_the_message_and_the_base_to_nothing(monkeypatch):
    """decode_images at a given camera (two rounds with the pose Jacobian): the marked render, 8-bit, gives the
    message; the base's own render leaves nothing to explain."""
    from gsticker_plugin.decoders.fieldimage import decode_images

    sc = marked_scene(monkeypatch, torch.tensor([1, 0, 1, 1, 0, 0, 1, 0]))
    key, ref, cam, marked, base = sc.key, sc.ref, sc.cam, sc.marked, sc.base
    pictures = [(x * 255).round() / 255 for x in (marked, base)]
    dec = decode_images(key, ref, pictures, seed=0, cameras=[cam, cam])
    assert dec["matches"].tolist()[0] == 8 and dec["image"][0]["explained"] > 0.5
    assert dec["image"][1]["explained"] < 0.05 and dec["matches"].tolist()[1] < 8


def test_a_picture_of_a_recoloured_copy_is_read_through_a_colour_map_of_the_base_samples(monkeypatch):
    """A copy whose every sample colour was changed (channels rotated and darkened, as a recolour edits the run):
    at its camera the picture is read through the colour map fitted from the base (the map explains nearly all of
    its difference from the base render) and gives the message; without the map the same fit explains little of the
    picture (0.01 against 0.74 here)."""
    from gsticker_plugin.decoders.fieldimage import decode_images, read_at_camera, recolouring_at
    from gsticker_plugin.decoders.fit import tie_generator

    message = torch.tensor([0, 1, 1, 0, 1, 0, 0, 1])
    sc = marked_scene(monkeypatch, message, recolour=lambda c: 0.8 * c[..., [1, 2, 0]] + 0.1)
    model, cam, key, ref, recoloured = sc.model, sc.cam, sc.key, sc.ref, sc.marked
    picture = (recoloured * 255).round() / 255
    rec = recolouring_at(model, picture, cam)
    assert rec is not None and rec.reads and rec.share > 0.95
    dec = decode_images(key, ref, [picture], seed=0, cameras=[cam])
    assert dec["image"][0]["color_map"] and dec["matches"].tolist() == [8]
    plain, _, _ = read_at_camera(ref, picture, cam, tie_generator(0), 2)
    assert plain["explained"] < 0.5 * dec["image"][0]["explained"]


def test_a_blurred_picture_is_read_as_the_blur_shows_the_base_and_a_plain_one_as_it_is(monkeypatch):
    """The marked render blurred (sigma 1 px, as a re-poster's resize or filter does): the blur is matched from the
    picture and the base alone, the base render and the mark's change are blurred alike, and the message is read;
    the plain render is matched to no degradation."""
    from gsticker_plugin.attacks import gaussian_blur
    from gsticker_plugin.decoders.fieldimage import decode_images, matched_degradation

    sc = marked_scene(monkeypatch, torch.tensor([1, 1, 0, 1, 0, 0, 1, 0]), side=48)
    cam, key, ref, base, marked = sc.cam, sc.key, sc.ref, sc.base, sc.marked
    blurred = gaussian_blur(marked.permute(2, 0, 1)[None], 1.0)[0].permute(1, 2, 0)
    assert matched_degradation(marked, base.reshape(-1, 3)).name == "none"
    assert matched_degradation(blurred, base.reshape(-1, 3)).name == "blur"
    dec = decode_images(key, ref, [blurred, marked], seed=0, cameras=[cam, cam])
    assert dec["image"][0]["degradation"].startswith("blur=") and dec["image"][1]["degradation"] == "none"
    assert dec["matches"].tolist() == [8, 8]


def tiny_planes():
    from nerfstudio.field_components.encodings import TensorVMEncoding

    torch.manual_seed(0)
    return TensorVMEncoding(resolution=16, num_components=3, init_scale=0.5)


def test_plane_patterns_are_smooth_unit_tables_drawn_from_the_seed_alone():
    shape = (3, 4, 32, 32)
    a, b = FM.plane_patterns(shape, 4, 6, seed=2), FM.plane_patterns(shape, 4, 6, seed=2)
    assert a.shape == (6, *shape) and torch.equal(a, b) and not torch.equal(a, FM.plane_patterns(shape, 4, 6, seed=3))
    assert torch.allclose(a.flatten(1).std(dim=1), torch.ones(6), atol=1e-5)
    step = (a[..., 1:, :] - a[..., :-1, :]).abs().mean()  # neighbours on the fine grid differ little: drawn coarse
    assert float(step) < 0.2 * float(a.abs().mean())


def test_plane_features_are_the_exact_change_of_the_density_before_its_relu():
    """TensoRF's density is linear in its planes: ``pre(planes + a sum_k s_k P_k / sqrt(K)) - pre(planes)`` is
    ``a * features @ s`` to float precision, at any amplitude."""
    enc = tiny_planes()
    pats = FM.plane_patterns(tuple(enc.plane_coef.shape), 4, 8, seed=1)
    x = torch.rand(200, 3) * 2 - 1
    pre, feats = FM.plane_features(enc, x, pats)
    signs, a = torch.tensor([1.0, -1, 1, 1, -1, -1, 1, -1]), 0.7
    with torch.no_grad():
        assert torch.allclose(pre, enc(x).sum(-1), atol=1e-5)
        saved = enc.plane_coef.data
        enc.plane_coef.data = FM.marked_table(saved, pats, signs, a)
        marked = enc(x).sum(-1)
        enc.plane_coef.data = saved
    assert torch.allclose(marked - pre, a * feats @ signs, atol=1e-4)
    assert torch.equal(enc.plane_coef.data, saved) and enc.num_components == 3  # the encoding is restored


def test_the_host_is_the_hash_table_of_a_torch_nerfacto_field_or_the_planes_of_a_tensorf_field(monkeypatch):
    from types import SimpleNamespace

    model = tiny_nerfacto(monkeypatch)
    assert FM.host_of(model.field) == "hash" and FM.marked_parameter(model.field) is FM.parts(model.field)[0].hash_table
    planes = SimpleNamespace(density_encoding=tiny_planes())
    assert FM.host_of(planes) == "planes" and FM.marked_parameter(planes) is planes.density_encoding.plane_coef
    with pytest.raises(GStickerError, match="--pipeline.mark sticker"):
        FM.host_of(nn.Linear(2, 2))


def test_pictures_of_a_tensorf_shared_run_are_refused_with_the_fix():
    from types import SimpleNamespace

    from gsticker_plugin.decoders.fieldimage import decode_images

    reference = SimpleNamespace(model=SimpleNamespace(field=SimpleNamespace(density_encoding=tiny_planes())))
    with pytest.raises(GStickerError, match="--load-config SUSPECT/config.yml"):
        decode_images(SimpleNamespace(num_bits=8), reference, [torch.zeros(4, 4, 3)], seed=0)


def tiny_tensorf(monkeypatch):
    """A randomly initialised TensoRF (vector-matrix planes at 16^3) with density in much of its box."""
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.models.tensorf import TensoRFModelConfig

    from gsticker_plugin import compat

    monkeypatch.setenv("GSTICKER_NO_DOWNLOAD", "1")
    compat.apply()
    torch.manual_seed(0)
    cfg = TensoRFModelConfig(
        init_resolution=16,
        final_resolution=16,
        upsampling_iters=(),
        num_samples=16,
        num_uniform_samples=16,
        num_den_components=3,
        num_color_components=3,
        appearance_dim=4,
        background_color="white",
    )
    model = cfg.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=2, metadata={})
    model.eval()
    with torch.no_grad():
        FM.planes_of(model.field).plane_coef.normal_(0.3, 0.5)
        FM.planes_of(model.field).line_coef.normal_(0.3, 0.5)
    return model


def box_camera(size: int = 8):
    from nerfstudio.cameras.cameras import Cameras

    c2w = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]])[None]
    return Cameras(
        camera_to_worlds=c2w, fx=1.2 * size, fy=1.2 * size, cx=size / 2, cy=size / 2, width=size, height=size
    )


def test_a_tensorf_view_holds_base_samples_with_density_that_any_field_answers_at_their_positions(monkeypatch):
    """The samples a TensoRF view keeps hold density, at most ``max_samples`` of them, and the base's density read
    back at their world positions through the field's public ``get_density`` is ``relu(pre)`` of the planes there."""
    model = tiny_tensorf(monkeypatch)
    pats = FM.plane_patterns(tuple(FM.planes_of(model.field).plane_coef.shape), 4, 8, seed=1)
    view = FM.density_view(model, box_camera(), pats)
    assert view.pre.numel() > 50 and bool((view.pre > 0).all()) and view.features.shape == (view.pre.numel(), 8)
    assert view.accumulation.shape == (64,) and view.hw == (8, 8)
    assert torch.allclose(FM.probe_density(model, view.world), view.pre, atol=1e-5)
    assert FM.density_view(model, box_camera(), pats, max_samples=50).pre.numel() == 50


def test_the_density_decoder_reads_every_bit_of_marked_planes_and_none_of_the_base(monkeypatch):
    """A TensoRF suspect is read at the base's samples: planes marked with the signs give every bit; the base itself
    determines none (all undetermined: mismatches whatever the message); an independently drawn field reads bits
    that are not the message's."""
    import copy

    from gsticker_plugin.decoders.fieldmark import decode_density
    from gsticker_plugin.decoders.fit import UNDETERMINED, tie_generator

    base = tiny_tensorf(monkeypatch)
    planes = FM.planes_of(base.field).plane_coef
    pats = FM.plane_patterns(tuple(planes.shape), 4, 8, seed=1)
    signs = torch.tensor([1.0, -1, -1, 1, 1, -1, 1, -1])
    message = (signs > 0).long()
    view = FM.density_view(base, box_camera(), pats)
    marked = copy.deepcopy(base)
    with torch.no_grad():
        FM.planes_of(marked.field).plane_coef.data = FM.marked_table(planes.data, pats, signs, 0.05)
    bits, fit = decode_density(view, marked, 0.05, tie_generator(0))
    assert torch.equal(bits, message) and fit.explained > 0.99
    bits, fit = decode_density(view, base, 0.05, tie_generator(0))
    assert bool((bits == UNDETERMINED).all()) and fit.explained == 0.0
    other = copy.deepcopy(base)
    with torch.no_grad():
        FM.planes_of(other.field).plane_coef.normal_(0.3, 0.5, generator=torch.Generator().manual_seed(5))
    bits, fit = decode_density(view, other, 0.05, tie_generator(0))
    assert fit.explained < 0.2 and not torch.equal(bits, message)


def test_the_density_of_a_wrapping_model_is_read_from_the_model_it_wraps(monkeypatch):
    """A recolored run wraps the shared run's model: its density is the wrapped field's."""
    model = tiny_tensorf(monkeypatch)
    wrapper = nn.Module()
    wrapper.inner = model
    assert FM.density_field(wrapper) is model.field and FM.density_field(model) is model.field
    x = torch.rand(20, 3) - 0.5
    assert torch.equal(FM.probe_density(wrapper, x), FM.probe_density(model, x))
    with pytest.raises(GStickerError, match="no Nerfstudio field"):
        FM.density_field(nn.Linear(2, 2))


def test_a_resized_then_blurred_copy_is_read_at_the_base_frame_through_the_blur(monkeypatch):
    """The marked render enlarged 1.5x (Pillow's bicubic) and then blurred (sigma 1 px of the copy): at its camera the
    blur is matched against the base resized like the copy, and the copy read at the base's own intrinsics through
    both gives the message and explains more of the picture than the same read ignoring the blur."""
    from types import SimpleNamespace

    from gsticker_plugin.attacks import gaussian_blur
    from gsticker_plugin.decoders import framed as FR
    from gsticker_plugin.decoders.fieldimage import matched_degradation, read_framed
    from gsticker_plugin.decoders.fit import tie_generator
    from gsticker_plugin.decoders.framing import Framing

    message = torch.tensor([0, 1, 1, 0, 1, 1, 0, 1])
    sc = marked_scene(monkeypatch, message, side=32)
    ref = sc.ref
    ref.pipeline = SimpleNamespace(datamanager=SimpleNamespace(train_dataset=SimpleNamespace(cameras=sc.cam)))
    framing = Framing(1.5, 1.5, 0.0, 0.0)
    copy = FR.warp_to_picture(sc.marked.permute(2, 0, 1), framing, 48, 48, "bicubic")[0]
    picture = (gaussian_blur(copy[None], 1.0)[0].permute(1, 2, 0).clamp(0, 1) * 255).round() / 255
    camera = FR.framed_camera(sc.cam, framing, 48, 48)
    resized_base = FR.resampled_renderer(sc.cam, "bicubic")(sc.model, camera, ("rgb",))["rgb"][0]
    blur = matched_degradation(picture, resized_base.reshape(-1, 3))
    assert blur.name == "blur"
    read, _, _ = read_framed(ref, picture, camera, tie_generator(0), 2, degradation=blur)
    assert read["bits"].tolist() == message.tolist() and read["degradation"].startswith("blur=")
    plain, _, _ = read_framed(ref, picture, camera, tie_generator(0), 2)
    assert plain["explained"] < read["explained"]
