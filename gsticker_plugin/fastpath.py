"""The fast path: the base is frozen, so its ray samples, densities and colours never change.

For a pool of views (training cameras and novel orbit cameras) we render the base once, keep the clean
image and, for the rays that hit something, the final samples (positions, deltas, base density, colour).
A training step then only evaluates the sticker at gated samples and re-composites those rays: no base
network runs inside the loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence

import torch
import torch.nn.functional as F
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import composite, message_to_signs, render_weights


@dataclass
class ViewCache:
    """One pool view: the clean render and the samples of its active rays."""

    image: Float[Tensor, "H W 3"]
    active: Tensor  # [A] flat ray indices
    positions: Tensor  # [A S 3]
    deltas: Tensor  # [A S 1]
    density: Tensor  # [A S 1] (float32: densities span orders of magnitude)
    rgb: Tensor  # [A S 3]
    novel: bool = False

    @property
    def hw(self):
        return self.image.shape[0], self.image.shape[1]

    def nbytes(self) -> int:
        return sum(
            t.numel() * t.element_size()
            for t in (self.image, self.active, self.positions, self.deltas, self.density, self.rgb)
        )


def orbit_cameras(cameras: Cameras, num: int, generator: torch.Generator, max_tilt_deg: float = 20.0) -> Cameras:
    """Novel cameras: random training cameras rotated about the world z axis through the origin (any yaw)
    and tilted by up to ``max_tilt_deg`` about the horizontal axis, keeping their intrinsics."""
    n = cameras.shape[0]
    idx = torch.randint(0, n, (num,), generator=generator)
    c2w = cameras.camera_to_worlds[idx].clone()  # [num 3 4]
    yaw = (torch.rand(num, generator=generator) * 2 - 1) * math.pi
    tilt = (torch.rand(num, generator=generator) * 2 - 1) * math.radians(max_tilt_deg)
    out = []
    for i in range(num):
        cz, sz = math.cos(yaw[i]), math.sin(yaw[i])
        rz = torch.tensor([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
        pos = rz @ c2w[i, :, 3]
        axis = torch.linalg.cross(pos, torch.tensor([0.0, 0.0, 1.0]))
        if axis.norm() > 1e-6:
            rt = axis_angle_matrix(axis / axis.norm(), float(tilt[i]))
        else:
            rt = torch.eye(3)
        r = rt @ rz
        out.append(torch.cat([r @ c2w[i, :, :3], (r @ c2w[i, :, 3:])], dim=1))
    return cameras_at(cameras, idx, out)


def axis_angle_matrix(axis: Float[Tensor, " 3"], angle: float) -> Float[Tensor, "3 3"]:
    """Rotation by ``angle`` (radians) about the unit vector ``axis`` (Rodrigues' formula)."""
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def cameras_at(cameras: Cameras, idx: Tensor, c2w: List[Tensor]) -> Cameras:
    """Cameras with the intrinsics of ``cameras[idx]`` and the poses ``c2w`` (one [3 4] per index)."""
    return Cameras(
        camera_to_worlds=torch.stack(c2w) if c2w else torch.zeros(0, 3, 4),
        fx=cameras.fx[idx],
        fy=cameras.fy[idx],
        cx=cameras.cx[idx],
        cy=cameras.cy[idx],
        width=cameras.width[idx],
        height=cameras.height[idx],
        camera_type=cameras.camera_type[idx],
    )


def camera_layout(cameras: Cameras, max_spread_deg: float = 90.0) -> str:
    """``"orbit"`` when the cameras look at the scene from around it (two viewing directions more than
    ``max_spread_deg`` apart), else ``"capture"`` (a forward-facing capture: every camera faces one way)."""
    fwd = -cameras.camera_to_worlds[:, :3, 2].float()
    fwd = fwd / fwd.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = (fwd @ fwd.T).clamp(-1.0, 1.0)
    return "orbit" if float(torch.rad2deg(torch.acos(cos.min()))) > max_spread_deg else "capture"


def capture_cameras(
    cameras: Cameras, num: int, generator: torch.Generator, jitter_deg: float = 5.0, jitter_share: float = 0.1
) -> Cameras:
    """Novel cameras within a capture's own trajectory: between two random training cameras (position and
    viewing direction interpolated), moved by up to ``jitter_share`` of the trajectory's extent and turned by up
    to ``jitter_deg``, keeping the first camera's intrinsics."""
    n = cameras.shape[0]
    c2w = cameras.camera_to_worlds.float()
    i = torch.randint(0, n, (num,), generator=generator)
    j = torch.randint(0, n, (num,), generator=generator)
    t = torch.rand(num, 1, generator=generator)
    extent = (c2w[:, :, 3].amax(dim=0) - c2w[:, :, 3].amin(dim=0)).norm()
    move = (torch.rand(num, 3, generator=generator) * 2 - 1) * jitter_share * extent
    axis = torch.randn(num, 3, generator=generator)
    angle = (torch.rand(num, generator=generator) * 2 - 1) * math.radians(jitter_deg)
    pos = (1 - t) * c2w[i, :, 3] + t * c2w[j, :, 3] + move
    back = (1 - t) * c2w[i, :, 2] + t * c2w[j, :, 2]
    up = (1 - t) * c2w[i, :, 1] + t * c2w[j, :, 1]
    out = []
    for k in range(num):
        z = back[k] / back[k].norm().clamp_min(1e-12)
        x = torch.linalg.cross(up[k], z)
        x = x / x.norm().clamp_min(1e-12)
        r = torch.stack([x, torch.linalg.cross(z, x), z], dim=1)
        turn = axis_angle_matrix(axis[k] / axis[k].norm().clamp_min(1e-12), float(angle[k]))
        out.append(torch.cat([turn @ r, pos[k][:, None]], dim=1))
    return cameras_at(cameras, i, out)


def novel_cameras(cameras: Cameras, num: int, generator: torch.Generator, layout: str = "auto") -> Cameras:
    """Novel cameras that fit the scene (``layout="auto"``: :func:`camera_layout`): :func:`orbit_cameras` around an
    object, :func:`capture_cameras` within a forward-facing capture's trajectory."""
    if (camera_layout(cameras) if layout == "auto" else layout) == "orbit":
        return orbit_cameras(cameras, num, generator)
    return capture_cameras(cameras, num, generator)


def coverage(view: ViewCache, threshold: float = 0.5) -> float:
    """Share of a cached view's pixels whose accumulation exceeds ``threshold`` (how much of it sees the scene)."""
    acc = render_weights(view.density, view.deltas).sum(dim=-2).squeeze(-1)
    h, w = view.hw
    return float((acc > threshold).sum()) / float(h * w)


@torch.no_grad()
def cache_view(
    model,
    camera: Cameras,
    novel: bool,
    min_density: Optional[float] = None,
    outputs_into: Optional[Dict[str, Tensor]] = None,
    full_precision: bool = False,
    message: Optional[Tensor] = None,
) -> ViewCache:
    """Render one camera with the sticker off, recording the final field's samples.

    ``outputs_into``: a dict that receives the render's outputs (accumulation, depth, ...), CPU float.
    ``full_precision``: keep positions and colours in float32 (the training pool stores them in half).
    ``message``: render with the sticker of this message on and record the base's density and colour at the
    samples the marked model draws (see ``capture_final_samples``); outputs and image are then the marked ones.
    """
    with model.capture_final_samples(message) as records:
        outputs = model.get_outputs_for_camera(camera)
    if outputs_into is not None:
        outputs_into.update({k: v.detach().float().cpu() for k, v in outputs.items() if isinstance(v, Tensor)})
    image = outputs["rgb"].detach().float().cpu()
    h, w = image.shape[:2]
    pos = torch.cat([r["positions"].reshape(-1, *r["positions"].shape[-2:]) for r in records]).cpu()
    deltas = torch.cat([r["deltas"].reshape(-1, *r["deltas"].shape[-2:]) for r in records]).cpu()
    density = torch.cat([r["density"].reshape(-1, *r["density"].shape[-2:]) for r in records]).float().cpu()
    rgb = torch.cat([r["rgb"].reshape(-1, *r["rgb"].shape[-2:]) for r in records]).cpu()
    if pos.shape[0] != h * w:
        raise GStickerError(
            f"captured {pos.shape[0]} rays for a {h}x{w} image: the base does not render a fixed number of samples "
            "per ray (packed samples, e.g. instant-ngp); watermark a nerfacto, tensorf or vanilla-nerf base"
        )
    thr = 0.0 if min_density is None else min_density
    active = (density.squeeze(-1) > thr).any(dim=-1).nonzero().squeeze(-1)
    low = (lambda t: t.float()) if full_precision else (lambda t: t.half())
    return ViewCache(
        image=image,
        active=active,
        positions=low(pos[active]),
        deltas=deltas[active].float(),
        density=density[active],
        rgb=low(rgb[active]),
        novel=novel,
    )


def render_cached(view: ViewCache, wrap, message: Tensor, background: Tensor) -> tuple:
    """Watermarked render of a cached view: the clean image plus the sticker's change on active rays.

    Returns the image [H W 3] and the gate values psi at the active samples (for the sparsity loss).
    """
    delta, psi = wrap.delta(view.density, view.positions.float(), message)
    return with_density_change(view, delta, background).clamp(0.0, 1.0), psi


def with_density_change(view: ViewCache, delta: Tensor, background: Tensor) -> Float[Tensor, "H W 3"]:
    """The cached view's clean image plus the colour change of adding ``delta`` to its samples' density (unclamped)."""
    h, w = view.hw
    rgb = view.rgb.float()
    marked, _ = composite(torch.relu(view.density + delta), rgb, view.deltas, background)
    clean, _ = composite(view.density, rgb, view.deltas, background)
    flat = view.image.reshape(-1, 3)
    return (flat + torch.zeros_like(flat).index_add(0, view.active, marked - clean)).reshape(h, w, 3)


def pool_memory_mb(views: List[ViewCache]) -> float:
    return sum(v.nbytes() for v in views) / 2**20


def render_offset(
    view: ViewCache, wrap, offset: Callable[[Tensor], Tensor], background: Tensor, clamp: bool = True
) -> Float[Tensor, "H W 3"]:
    """Render of a cached view with ``psi * scale * offset(x)`` added to the density where the gate is open
    (``offset`` maps normalized positions [N 3] to [N 1]); ``clamp=False`` keeps unclamped colours (derivatives)."""
    psi, open_ = wrap.open_samples(view.density)
    delta = torch.zeros_like(view.density)
    if open_.any():
        delta[open_] = psi[open_] * wrap.gate.scale * offset(wrap.normalize(view.positions.float()[open_]))
    out = with_density_change(view, delta, background)
    return out.clamp(0.0, 1.0) if clamp else out


def render_signs(
    view: ViewCache, wrap, signs: Tensor, background: Tensor, gain: float = 1.0, clamp: bool = True
) -> Float[Tensor, "H W 3"]:
    """Render with the (bilinear) sticker at continuous message signs (+-1 for bits), its change scaled by ``gain``."""
    sticker = wrap.sticker
    return render_offset(
        view, wrap, lambda pos: gain * sticker.mix(sticker.features(pos), signs.to(pos)), background, clamp
    )


def sign_gram(view: ViewCache, wrap, message: Tensor, background: Tensor, blur: float = 0.0) -> Float[Tensor, "K K"]:
    """``J^T J`` of the render's per-bit change at the corner ``message``: J[(r, c), b] = d colour / d s_b of every
    active ray and channel (the informed image decoder's columns there). Differentiable in the sticker's weights
    through d m / d s (the compositing's derivative in the density is held fixed). ``blur`` > 0: the columns are
    laid out as images and blurred by a Gaussian of that std (px) first, the low-pass of a blur or JPEG."""
    return sign_grams(view, wrap, message, background, (blur,))[0]


def sign_grams(
    view: ViewCache, wrap, message: Tensor, background: Tensor, blurs: Sequence[float]
) -> List[Float[Tensor, "K K"]]:
    """:func:`sign_gram` at each blur of ``blurs``, from one evaluation of the columns."""
    sticker = wrap.sticker
    psi, open_ = wrap.open_samples(view.density)
    k = sticker.num_bits
    if not open_.any():
        return [torch.zeros(k, k, device=view.density.device) for _ in blurs]
    feats = sticker.features(wrap.normalize(view.positions.float()[open_]))  # [N K]
    m = sticker.mix(feats, message_to_signs(message).to(feats))  # [N 1]
    ddelta = (psi[open_] * wrap.gate.scale) * sticker.mix_jacobian(feats, m)  # [N K]: d delta / d s
    with torch.enable_grad():
        delta = torch.zeros_like(view.density)
        delta[open_] = (psi[open_] * wrap.gate.scale * m).detach()
        delta.requires_grad_(True)
        out, _ = composite(torch.relu(view.density + delta), view.rgb.float(), view.deltas, background)
        grads = [torch.autograd.grad(out[:, c].sum(), delta, retain_graph=c < 2)[0][open_] for c in range(3)]
    ray = open_.nonzero()[:, 0]
    cols = [
        torch.zeros(view.density.shape[0], k, device=ddelta.device, dtype=ddelta.dtype).index_add(0, ray, g * ddelta)
        for g in grads
    ]
    grams = []
    for blur in blurs:
        j = torch.cat([blur_columns(c, view, blur) for c in cols] if blur > 0 else cols)  # [3A K] (blurred: [3HW K])
        grams.append(j.T @ j)
    return grams


def blur_columns(cols: Float[Tensor, "A K"], view: ViewCache, sigma: float) -> Float[Tensor, "HW K"]:
    """Per-ray columns of one channel laid out on the view's image (zero off the active rays), each blurred by a
    Gaussian of std ``sigma`` px; one row per pixel."""
    h, w = view.hw
    img = torch.zeros(h * w, cols.shape[1], device=cols.device, dtype=cols.dtype)
    img = img.index_add(0, view.active.to(cols.device), cols).reshape(h, w, -1)
    return smoothed(img, sigma).reshape(h * w, -1)


def smoothed(img: Float[Tensor, "H W C"], sigma: float) -> Float[Tensor, "H W C"]:
    """``img`` blurred by a separable Gaussian of ``sigma`` px (edges replicated); as it is for ``sigma <= 0``. Any
    number of channels and float64, unlike the blur attack (``attacks.gaussian_blur``: RGB batches)."""
    if sigma <= 0:
        return img
    r = int(3 * sigma + 0.5)
    t = torch.arange(-r, r + 1, dtype=torch.float64)
    k = torch.exp(-(t**2) / (2 * sigma**2))
    k = (k / k.sum()).to(img.dtype)
    x = img.permute(2, 0, 1)[:, None]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return x[:, 0].permute(1, 2, 0)


def noise_variance(gram: Float[Tensor, "K K"], noise: float) -> Float[Tensor, ""]:
    """Mean variance of the least-squares message estimate under white image noise of std ``noise``:
    ``noise^2 * mean diag((G + eps I)^-1)``, eps a 1e-6 share of the mean diagonal (keeps it finite)."""
    k = gram.shape[0]
    eye = torch.eye(k, dtype=torch.float64, device=gram.device)
    g = gram.double()
    eps = 1e-6 * torch.diagonal(g).mean().detach().clamp_min(1e-30)
    return (noise**2) * torch.diagonal(torch.linalg.inv(g + eps * eye)).mean()


def condition_term(grams: List[Tensor], noise: float, scale_free: bool) -> Float[Tensor, ""]:
    """The conditioning loss's term: the mean over ``grams`` of the log estimate variance at ``noise``; with
    ``scale_free`` each less the log of its mean energy (trace / bits), so scaling the change leaves it unchanged."""
    terms = []
    for gram in grams:
        term = torch.log(noise_variance(gram, noise))
        if scale_free:
            term = term + torch.log(torch.diagonal(gram).mean().double().clamp_min(1e-30))
        terms.append(term)
    return torch.stack(terms).mean()
