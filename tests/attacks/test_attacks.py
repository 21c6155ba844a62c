"""Tests for gsticker_plugin.attacks (small CPU tensors)."""

from __future__ import annotations

import math

import pytest
import torch

from gsticker_plugin import attacks as A
from gsticker_plugin.metrics import psnr


def rand_img(b=2, h=32, w=32, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, h, w, generator=g, dtype=dtype)


def smooth_img(b=2, h=32, w=32):
    y = torch.linspace(0, 1, h).view(1, 1, h, 1)
    x = torch.linspace(0, 1, w).view(1, 1, 1, w)
    r = 0.5 + 0.3 * torch.sin(2 * math.pi * x) * torch.cos(math.pi * y)
    gch = 0.3 + 0.5 * x * y
    bch = 0.7 - 0.4 * y + 0.0 * x
    img = torch.cat([r.expand(1, 1, h, w), gch.expand(1, 1, h, w), bch.expand(1, 1, h, w)], dim=1)
    return img.expand(b, 3, h, w).contiguous()


# name -> (strength used for generic checks, strength that must be an identity)
CASES = {
    "noise": (0.1, 0.0),
    "rotate": (30.0, 0.0),
    "crop": (0.25, 0.0),
    "blur": (1.0, 0.0),
    "hue": (0.3, 0.0),
    "jpeg": (50.0, None),
    "resize": (0.5, 1.0),
}


def test_registry_names():
    assert set(A.ATTACKS) == {"noise", "rotate", "crop", "blur", "hue", "jpeg", "resize"}
    assert tuple(A.ATTACKS) == A.ATTACK_NAMES


@pytest.mark.parametrize("name", list(CASES))
def test_shape_range_dtype_and_change(name):
    img = rand_img()
    strength, _ = CASES[name]
    out = A.ATTACKS[name](img, strength, generator=torch.Generator().manual_seed(0))
    assert out.shape == img.shape and out.dtype == img.dtype and out.device == img.device
    assert out.min() >= 0 and out.max() <= 1
    assert (out - img).abs().max() > 1e-3  # it actually does something
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("name", ["noise", "rotate", "blur", "hue", "resize"])
def test_half_precision_dtype_kept(name):
    img = rand_img(b=1, h=16, w=16).to(torch.bfloat16)
    out = A.ATTACKS[name](img, CASES[name][0])
    assert out.dtype == torch.bfloat16 and out.shape == img.shape


@pytest.mark.parametrize("name", [n for n, (_, ident) in CASES.items() if ident is not None])
def test_identity_at_zero_strength(name):
    img = rand_img()
    _, ident = CASES[name]
    out = A.ATTACKS[name](img, ident, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(out, img, atol=1e-5), (out - img).abs().max()


@pytest.mark.parametrize("name", list(CASES))
def test_gradients_flow(name):
    img = rand_img(b=2, h=16, w=16).mul(0.8).add(0.1).requires_grad_(True)
    out = A.ATTACKS[name](img, CASES[name][0], generator=torch.Generator().manual_seed(0))
    w = torch.linspace(-1, 1, out.numel()).view_as(out)
    (out * w).sum().backward()
    assert img.grad is not None
    assert torch.isfinite(img.grad).all()
    assert img.grad.abs().sum() > 0


def test_noise_std_and_seed():
    img = torch.full((2, 3, 32, 32), 0.5)
    g1, g2 = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    a, b = A.gaussian_noise(img, 0.05, g1), A.gaussian_noise(img, 0.05, g2)
    assert torch.equal(a, b)
    assert (a - img).std().item() == pytest.approx(0.05, rel=0.1)  # sigma is the std, not the variance
    per = A.gaussian_noise(img, torch.tensor([0.0, 0.1]), torch.Generator().manual_seed(1))
    assert torch.equal(per[0], img[0]) and (per[1] - img[1]).std().item() == pytest.approx(0.1, rel=0.1)


def test_rotate_90_equals_rot90_and_fill_white():
    img = rand_img(b=2)
    out = A.rotate(img, 90.0)
    ref = torch.rot90(img, k=1, dims=(-2, -1))
    assert torch.allclose(out[..., 1:-1, 1:-1], ref[..., 1:-1, 1:-1], atol=1e-4)
    assert not torch.allclose(out, torch.rot90(img, k=-1, dims=(-2, -1)), atol=1e-2)  # direction matters
    black = torch.zeros(1, 3, 32, 32)
    r45 = A.rotate(black, 45.0)
    assert torch.allclose(r45[..., 0, 0], torch.ones(1, 3), atol=1e-5)  # corner: outside, white
    assert r45[..., 16, 16].abs().max() < 1e-5  # centre: black image content
    assert A.rotate(torch.ones(1, 3, 32, 32), 45.0, fill=0.0)[..., 0, 0].abs().max() < 1e-5
    per = A.rotate(img, torch.tensor([0.0, 90.0]))
    assert torch.allclose(per[0], img[0], atol=1e-5)
    assert torch.allclose(per[1, :, 1:-1, 1:-1], ref[1, :, 1:-1, 1:-1], atol=1e-4)


@pytest.mark.parametrize("share", [0.1, 0.25, 0.5, 1.0])
def test_cropout_share_rectangle_cover(share):
    img = torch.zeros(2, 3, 32, 32)
    cover = torch.ones(2, 3, 32, 32)
    out = A.cropout(img, share, cover=cover, generator=torch.Generator().manual_seed(3))
    for i in range(2):
        mask = out[i, 0] > 0.5
        assert torch.equal(out[i, 0], out[i, 1]) and torch.equal(out[i, 0], out[i, 2])
        assert mask.float().mean().item() == pytest.approx(share, abs=0.03)
        rows, cols = mask.any(1), mask.any(0)
        assert torch.equal(mask, rows[:, None] & cols[None, :])  # one axis-aligned rectangle


def test_cropout_fill_and_seed():
    img = torch.zeros(1, 3, 32, 32)
    a = A.cropout(img, 0.25, fill=0.7, generator=torch.Generator().manual_seed(5))
    b = A.cropout(img, 0.25, fill=0.7, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
    vals = a.unique()
    assert vals.numel() == 2 and vals[0].item() == 0.0 and vals[1].item() == pytest.approx(0.7)
    assert (a > 0).float().mean().item() == pytest.approx(0.25, abs=0.03)
    with pytest.raises(ValueError):
        A.cropout(img, 1.5)


def test_blur_kernel_and_small_sigma_is_identity():
    assert A.blur_kernel_size(0.1) == 3
    assert A.blur_kernel_size(1.0) == 7
    assert A.blur_kernel_size(2.5) == 17
    img = rand_img()
    assert (A.gaussian_blur(img, 0.1) - img).abs().max() < 1e-6  # "sigma 0.1" is a no-op
    blurred = A.gaussian_blur(img, 1.0)
    assert blurred.std() < 0.6 * img.std()  # white noise loses most of its variance
    per = A.gaussian_blur(img, torch.tensor([0.0, 1.0]))
    assert torch.equal(per[0], img[0]) and torch.allclose(per[1], blurred[1], atol=1e-6)


def test_hue_shift_properties():
    img = rand_img()
    twice = A.hue_shift(A.hue_shift(img, 0.5), 0.5)
    assert torch.allclose(twice, img, atol=1e-4)
    assert (A.hue_shift(img, 0.5) - img).abs().max() > 0.1
    red = torch.zeros(1, 3, 4, 4)
    red[:, 0] = 1.0
    green, blue = torch.zeros_like(red), torch.zeros_like(red)
    green[:, 1] = 1.0
    blue[:, 2] = 1.0
    assert torch.allclose(A.hue_shift(red, 1 / 3), green, atol=1e-4)
    assert torch.allclose(A.hue_shift(red, -1 / 3), blue, atol=1e-4)
    gray = torch.rand(2, 1, 8, 8, generator=torch.Generator().manual_seed(2)).expand(2, 3, 8, 8).contiguous()
    assert torch.allclose(A.hue_shift(gray, 0.37), gray, atol=1e-6)
    with pytest.raises(ValueError):
        A.hue_shift(img, 0.7)


def test_jpeg_quality_and_odd_sizes():
    img = smooth_img()
    out = A.jpeg(img, 90)
    assert (out - img).abs().max() > 1e-4
    assert (psnr(out, img) > 25).all()
    low = A.jpeg(img, 5)
    assert (psnr(low, img) < psnr(out, img)).all()
    odd = A.jpeg(rand_img(b=1, h=20, w=24), 50)  # not multiples of 16
    assert odd.shape == (1, 3, 20, 24)
    per = A.jpeg(img, torch.tensor([90.0, 5.0]))
    assert torch.allclose(per[0], out[0], atol=1e-5) and torch.allclose(per[1], low[1], atol=1e-5)
    with pytest.raises(ValueError):
        A.jpeg(img, 0)


def test_resize_smooths_noise():
    img = rand_img()
    out = A.resize(img, 0.5)
    assert out.std() < 0.8 * img.std()
    # antialiased 4x downscale averages ~16 pixels per output pixel; plain bilinear only 4 (std ratio ~0.5)
    assert A.resize(img, 0.25).std() < 0.3 * img.std()
    smooth = smooth_img()
    assert (psnr(A.resize(smooth, 0.5), smooth) > 30).all()
    per = A.resize(img, torch.tensor([1.0, 0.5]))
    assert torch.equal(per[0], img[0]) and torch.allclose(per[1], out[1], atol=1e-6)


def test_parse_attack_spec_ok():
    spec = "noise=0.1,rotate=30,crop=0.25,blur=1,jpeg=50,hue=0.3,resize=0.5"
    assert A.parse_attack_spec(spec) == [
        ("noise", 0.1),
        ("rotate", 30.0),
        ("crop", 0.25),
        ("blur", 1.0),
        ("jpeg", 50.0),
        ("hue", 0.3),
        ("resize", 0.5),
    ]
    assert A.parse_attack_spec(" Noise = 0.2 , ") == [("noise", 0.2)]
    assert A.parse_attack_spec("") == []


@pytest.mark.parametrize(
    "spec, needle",
    [
        ("gamma=2", "use one of"),
        ("noise", "NAME=STRENGTH"),
        ("noise=abc", "not a number"),
        ("jpeg=0", "1..100"),
        ("jpeg=101", "1..100"),
        ("crop=1.5", "[0,1]"),
        ("hue=0.6", "[-0.5,0.5]"),
        ("resize=0", "(0,1]"),
        ("noise=-0.1", ">= 0"),
        ("blur=nan", "blur sigma"),
    ],
)
def test_parse_attack_spec_errors(spec, needle):
    with pytest.raises(ValueError) as e:
        A.parse_attack_spec(spec)
    msg = str(e.value)
    assert needle in msg and "\n" not in msg


def test_apply_attacks_in_order():
    img = smooth_img()
    out = A.apply_attacks(img, "blur=1,resize=0.5")
    assert torch.allclose(out, A.resize(A.gaussian_blur(img, 1.0), 0.5))
    assert not torch.allclose(A.apply_attacks(img, "rotate=30,crop=0.5"), A.apply_attacks(img, "crop=0.5,rotate=30"))
    assert torch.equal(A.apply_attacks(img, ""), img)
    assert torch.allclose(A.apply_attacks(img, [("hue", 0.5), ("hue", 0.5)]), img, atol=1e-4)
    with pytest.raises(ValueError):
        A.apply_attacks(img, [("jpeg", 500)])


def test_modules_match_functions():
    img = rand_img(b=1, h=16, w=16)
    assert torch.equal(A.Rotate(20.0)(img), A.rotate(img, 20.0))
    assert torch.equal(A.GaussianBlur(1.0)(img), A.gaussian_blur(img, 1.0))
    assert torch.equal(A.HueShift(0.2)(img), A.hue_shift(img, 0.2))
    assert torch.equal(A.JPEG(70)(img), A.jpeg(img, 70))
    assert torch.equal(A.Resize(0.5)(img), A.resize(img, 0.5))
    g1, g2 = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    assert torch.equal(A.GaussianNoise(0.1)(img, generator=g1), A.gaussian_noise(img, 0.1, g2))
    g1, g2 = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    assert torch.equal(A.Cropout(0.3)(img, generator=g1), A.cropout(img, 0.3, generator=g2))


def test_random_distortion_deterministic_and_mixed():
    img = rand_img(b=8, h=16, w=16)
    rd = A.RandomDistortion(A.RandomDistortionConfig())
    a = rd(img, generator=torch.Generator().manual_seed(11))
    b = rd(img, generator=torch.Generator().manual_seed(11))
    c = rd(img, generator=torch.Generator().manual_seed(12))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    assert a.shape == img.shape and a.dtype == img.dtype and a.min() >= 0 and a.max() <= 1
    names, strengths = rd.sample(200, torch.Generator().manual_seed(0))
    assert set(names) == set(A.ATTACK_NAMES) | {"identity"}
    assert 0.1 < names.count("identity") / 200 < 0.3
    for n, s in zip(names, strengths):
        if n == "jpeg":
            assert 50 <= s <= 100
        if n == "rotate":
            assert -30 <= s <= 30
        if n == "resize":
            assert 0.5 <= s <= 1


def test_random_distortion_per_image_and_grad():
    img = rand_img(b=6, h=16, w=16).requires_grad_(True)
    only_id = A.RandomDistortion(A.RandomDistortionConfig(p_identity=1.0))
    assert torch.equal(only_id(img, generator=torch.Generator().manual_seed(0)), img)
    cfg = A.RandomDistortionConfig(enabled=("crop",), crop_share=1.0, p_identity=0.0)
    cover = torch.zeros_like(img)
    out = A.RandomDistortion(cfg)(img, cover=cover, generator=torch.Generator().manual_seed(0))
    names, strengths = A.RandomDistortion(cfg).sample(6, torch.Generator().manual_seed(0))
    assert names == ["crop"] * 6
    shares = (out == 0).all(1).float().mean((1, 2))
    assert torch.allclose(shares, torch.tensor(strengths), atol=0.08)  # each image its own strength
    rd = A.RandomDistortion(A.RandomDistortionConfig(p_identity=0.0))
    rd(img, generator=torch.Generator().manual_seed(4)).sum().backward()
    assert img.grad is not None and torch.isfinite(img.grad).all()


def test_random_distortion_config_validation():
    with pytest.raises(ValueError):
        A.RandomDistortionConfig(enabled=("noise", "gamma"))
    with pytest.raises(ValueError):
        A.RandomDistortionConfig(jpeg_quality_min=0)
    with pytest.raises(ValueError):
        A.RandomDistortionConfig(p_identity=1.5)
    assert isinstance(A.RandomDistortionConfig(enabled=("noise",)).setup(), A.RandomDistortion)
