"""The camera of a suspect image, found against the owner's base: candidate poses, then Gauss-Newton on the pixels.

The informed image decoder needs each image's camera to a few hundredths of a pixel (docs/experiments/verify-notes.md). Without a
cameras file, :func:`estimate_camera` scores the base's renders at candidate poses (its training cameras and novel
ones drawn like the pool's) against the image at a few pixels' size, then refines the best ones by Levenberg-Marquardt
on the photometric residual (6 pose parameters, finite-difference Jacobian of the base render) from coarse to full
resolution. It uses the image and the owner's base only, never the owner's message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from gsticker_plugin.attacks.geometric import rotate
from gsticker_plugin.cameras import same_aspect
from gsticker_plugin.decoders import viewbank as VB
from gsticker_plugin.decoders.geometric import outputs_in_chunks, render_rays
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.fastpath import axis_angle_matrix, novel_cameras, smoothed

POSE = 6
"""Parameters of a pose change: axis-angle turn (3) and move (3), camera frame."""
FRAMED = 9
"""Parameters of a pose and framing change: the pose's 6, the log of the zoom and the principal point's move (px)."""
PRINCIPAL_STEP = 0.05
"""Finite-difference step (px) of the principal point in :func:`pose_columns`."""


def moved_camera(camera: Cameras, delta: Float[Tensor, " P"], distance: float = 1.0) -> Cameras:
    """``camera`` turned by the axis-angle ``delta[:3]`` (radians, camera frame) and moved by ``delta[3:6] *
    distance`` (camera frame); with :data:`FRAMED` entries also zoomed by ``exp(delta[6])`` (``fx``, ``fy``) and its
    principal point moved by ``delta[7:9]`` px (``cx``, ``cy``); one camera."""
    c2w = camera.camera_to_worlds[:1].detach().clone().float().cpu()
    r = c2w[0, :, :3]
    w = delta[:3].double()
    angle = float(w.norm())
    turn = axis_angle_matrix((w / angle).float(), angle) if angle > 0 else torch.eye(3)
    c2w[0, :, 3] = c2w[0, :, 3] + r @ (delta[3:6].float() * distance)
    c2w[0, :, :3] = r @ turn
    zoom, dcx, dcy = (
        (math.exp(float(delta[6])), float(delta[7]), float(delta[8])) if delta.numel() > POSE else (1, 0, 0)
    )
    return Cameras(
        camera_to_worlds=c2w,
        fx=camera.fx[:1].cpu() * zoom,
        fy=camera.fy[:1].cpu() * zoom,
        cx=camera.cx[:1].cpu() + dcx,
        cy=camera.cy[:1].cpu() + dcy,
        width=camera.width[:1].cpu(),
        height=camera.height[:1].cpu(),
        camera_type=camera.camera_type[:1].cpu(),
    )


def scaled_camera(camera: Cameras, height: int, width: int) -> Cameras:
    """``camera`` (one) with its intrinsics scaled to an image of ``height x width`` px."""
    sx = width / float(camera.width[0])
    sy = height / float(camera.height[0])
    return Cameras(
        camera_to_worlds=camera.camera_to_worlds[:1].detach().float().cpu(),
        fx=camera.fx[:1].cpu() * sx,
        fy=camera.fy[:1].cpu() * sy,
        cx=camera.cx[:1].cpu() * sx,
        cy=camera.cy[:1].cpu() * sy,
        width=width,
        height=height,
        camera_type=camera.camera_type[:1].cpu(),
    )


def camera_distance(camera: Cameras) -> float:
    """How far the camera is from the world origin (the scale of its translation steps); 1 at the origin."""
    d = float(camera.camera_to_worlds[0, :, 3].norm())
    return d if d > 1e-6 else 1.0


def channel_of(rgb: Float[Tensor, "... 3"], value: bool) -> Float[Tensor, "..."]:
    """What the pose fit compares: RGB as it is, or V = max(R, G, B) (unchanged by a hue shift)."""
    return rgb.amax(dim=-1, keepdim=True) if value else rgb


def area_resize(image: Float[Tensor, "H W 3"], height: int, width: int) -> Float[Tensor, "h w 3"]:
    """``image`` averaged down to ``height x width`` (area interpolation)."""
    x = image.float().permute(2, 0, 1)[None]
    return F.interpolate(x, size=(height, width), mode="area")[0].permute(1, 2, 0)


Window = Tuple[int, int, int, int]
"""Rows ``[r0, r1)`` and columns ``[c0, c1)`` of an image."""


def pixel_grid(height: int, width: int, window: Optional[Window] = None) -> Float[Tensor, "P 2"]:
    """Pixel-centre coordinates (row, column) of an image or of its ``window``, row-major, as nerfstudio's cameras
    take them."""
    r0, r1, c0, c1 = window if window is not None else (0, height, 0, width)
    ii, jj = torch.meshgrid(torch.arange(r0, r1), torch.arange(c0, c1), indexing="ij")
    return torch.stack([ii, jj], dim=-1).reshape(-1, 2).float() + 0.5


@torch.no_grad()
def render_cameras(
    model, cameras: Cameras, keys: Sequence[str] = ("rgb",), window: Optional[Window] = None
) -> Dict[str, Tensor]:
    """The model's outputs ``keys`` for every camera of ``cameras`` (all the same size), or for their ``window``, in
    one batched pass: ``{key: [N H W C]}`` on the CPU."""
    n = cameras.shape[0]
    r0, r1, c0, c1 = window if window is not None else (0, int(cameras.height[0]), 0, int(cameras.width[0]))
    h, w = r1 - r0, c1 - c0
    coords = pixel_grid(h, w, None).repeat(n, 1) + torch.tensor([float(r0), float(c0)])
    index = torch.arange(n).repeat_interleave(h * w)[:, None]
    bundle = cameras.to(model.device).generate_rays(
        camera_indices=index.to(model.device), coords=coords.to(model.device)
    )
    out = outputs_in_chunks(model, bundle.reshape((-1, 1)))
    return {k: out[k].reshape(n, h, w, -1).float().cpu() for k in keys}


Renderer = Callable[[Any, Cameras, Sequence[str]], Dict[str, Tensor]]
"""How a refinement renders the base at a camera: ``(model, camera, keys) -> {key: [1 H W C]}``, as
:func:`render_cameras`."""


def ncc(a: Float[Tensor, "N M"], b: Float[Tensor, " M"]) -> Float[Tensor, " N"]:
    """Normalised cross-correlation of each row of ``a`` with ``b``."""
    a = a - a.mean(dim=-1, keepdim=True)
    b = b - b.mean()
    return (a @ b) / (a.norm(dim=-1) * b.norm()).clamp_min(1e-12)


@dataclass
class PoseFit:
    """A camera found for an image and how well the base render at it explains the image."""

    camera: Cameras
    rms: float  # RMS of image minus base render at full size, on the fitted channel
    score: float  # NCC of the best candidate at the search size
    iterations: int
    history: List[Dict[str, Any]] = field(default_factory=list)
    resampler: Optional[str] = None
    """The resampling filter of a resized copy whose camera was refined as the copy was made
    (:func:`gsticker_plugin.decoders.framed.refine_resampled`); None for a render at the camera's own intrinsics."""


def projection(camera: Cameras, points: Float[Tensor, "P 3"]):
    """A function of the change ``delta`` (:data:`POSE` or :data:`FRAMED` entries, as :func:`moved_camera`) giving
    the pixel (row, column) of each world point in ``camera`` moved by it (nerfstudio's OpenGL convention: the camera
    looks down -z, y up)."""
    c2w = camera.camera_to_worlds[0].double().cpu()
    r, t = c2w[:, :3], c2w[:, 3]
    xc = (points.double() - t) @ r  # camera-frame points
    fx, fy = float(camera.fx[0]), float(camera.fy[0])
    cx, cy = float(camera.cx[0]), float(camera.cy[0])
    dist = camera_distance(camera)

    def pixels(delta: Tensor) -> Tensor:
        w, v = delta[:3], delta[3:6] * dist
        theta = torch.sqrt((w**2).sum() + 1e-30)
        k = w / theta
        # Rodrigues on every point: exp(-[w]x) (x - v), the point in the moved camera's frame
        x = xc - v
        cos, sin = torch.cos(theta), torch.sin(theta)
        kx = torch.linalg.cross(k.expand_as(x), x, dim=-1)
        rotated = x * cos - kx * sin + k * (x @ k)[:, None] * (1 - cos)
        z = (-rotated[:, 2]).clamp_min(1e-6)
        if delta.shape[0] > POSE:
            zoom = torch.exp(delta[6])
            return torch.stack(
                [cy + delta[8] - fy * zoom * rotated[:, 1] / z, cx + delta[7] + fx * zoom * rotated[:, 0] / z], dim=-1
            )
        return torch.stack([cy - fy * rotated[:, 1] / z, cx + fx * rotated[:, 0] / z], dim=-1)

    return pixels


def image_gradient(img: Float[Tensor, "H W C"]) -> Tuple[Tensor, Tensor]:
    """Central differences of ``img`` along rows and columns (one-sided at the border)."""
    x = img.permute(2, 0, 1)[None].double()
    pad = F.pad(x, (1, 1, 1, 1), mode="replicate")
    d_row = (pad[..., 2:, 1:-1] - pad[..., :-2, 1:-1]) / 2
    d_col = (pad[..., 1:-1, 2:] - pad[..., 1:-1, :-2]) / 2
    return d_row[0].permute(1, 2, 0), d_col[0].permute(1, 2, 0)


def surface_points(
    camera: Cameras, depth: Float[Tensor, "H W 1"], acc: Float[Tensor, "H W 1"], window: Optional[Window] = None
) -> Float[Tensor, "P 3"]:
    """The 3D point each pixel (of ``window``) sees (ray distance ``depth``); background pixels take the nearest
    surface depth within two pixels (an object's edge moves with the object)."""
    h, w = depth.shape[:2]
    d = depth[..., 0].double().clone()
    solid = acc[..., 0] > 0.5
    big = torch.where(solid, d, torch.full_like(d, 1e9))
    near = -F.max_pool2d(-big[None, None], 5, stride=1, padding=2)[0, 0]
    d = torch.where(solid, d, torch.where(near < 1e8, near, d))
    coords = pixel_grid(h, w) + (torch.tensor([float(window[0]), float(window[2])]) if window is not None else 0.0)
    bundle = camera.generate_rays(camera_indices=torch.zeros(h * w, 1, dtype=torch.long), coords=coords)
    return bundle.origins.double() + bundle.directions.double() * d.reshape(-1, 1)


def content_window(acc: Float[Tensor, "H W 1"], margin: int) -> Window:
    """The rows and columns where the render has content (accumulation above 0.01), widened by ``margin`` px; the
    whole image when it has none."""
    h, w = acc.shape[:2]
    mask = acc[..., 0] > 0.01
    if not bool(mask.any()):
        return (0, h, 0, w)
    rows = mask.any(dim=1).nonzero().squeeze(-1)
    cols = mask.any(dim=0).nonzero().squeeze(-1)
    return (
        max(0, int(rows[0]) - margin),
        min(h, int(rows[-1]) + 1 + margin),
        max(0, int(cols[0]) - margin),
        min(w, int(cols[-1]) + 1 + margin),
    )


def cauchy_weights(r: Tensor, robust: bool = True) -> Tensor:
    """Cauchy weights of the residuals ``r`` at three times their robust scale (1.4826 x the median absolute value);
    all ones when not ``robust``."""
    if not robust:
        return torch.ones_like(r)
    scale = 1.4826 * float(r.abs().median()) + 1e-3
    return 1.0 / (1.0 + (r / (3.0 * scale)) ** 2)


def lk_refine(
    model,
    camera: Cameras,
    target: Float[Tensor, "H W C"],
    value: bool,
    iterations: int,
    sigma: float = 0.0,
    robust: bool = True,
    extend: int = 1,
    render_blur: float = 0.0,
    trim: float = 1.0,
    free: int = POSE,
) -> Tuple[Cameras, float, int]:
    """Gauss-Newton (Lucas-Kanade with the base's depth) over the ``free`` parameters of ``camera`` (sized like
    ``target``; :data:`POSE`, or :data:`FRAMED` for the zoom and principal point too): the pixel motion of each surface point under a pose change times the base render's image gradient
    is the Jacobian; one render per step, damped and accepted only when the (Cauchy-weighted when ``robust``)
    residual drops; an accepted step is tried at 2, 4, ... up to ``extend`` times its length while the residual keeps
    dropping. Render and target are blurred by ``sigma`` px (a wider basin; and the render's gradient only follows
    its true derivative once blurred); the render by ``render_blur`` px more (an image blurred after rendering, so
    both sides hold the same blur). Returns the camera, the final RMS (over the ``trim`` share of pixels with the
    smallest residuals, :func:`trimmed_rms`) and the iterations taken."""
    dist = camera_distance(camera)
    lam = 1e-4
    keys = ("rgb", "expected_depth", "accumulation")
    h, w = target.shape[:2]
    full = render_cameras(model, camera, keys)
    window = content_window(full["accumulation"][0], int(3 * sigma + 3 * render_blur) + 6)
    r0_, r1_, c0_, c1_ = window
    # blur before cropping, so the window's border sees the image around it as the renders see themselves
    y = smoothed(target.double(), sigma)[r0_:r1_, c0_:c1_]
    rsigma = math.hypot(sigma, render_blur)

    def look(cam: Cameras):
        out = render_cameras(model, cam, keys, window)
        img = smoothed(channel_of(out["rgb"][0], value).double(), rsigma)
        return out, img, y - img

    cur = camera
    out = {k: v[:, r0_:r1_, c0_:c1_] for k, v in full.items()}  # the window of the render already made
    img = smoothed(channel_of(out["rgb"][0], value).double(), rsigma)
    r0 = y - img

    it = 0
    for it in range(1, iterations + 1):
        pts = surface_points(cur, out["expected_depth"][0], out["accumulation"][0], window)
        dp = torch.func.jacfwd(projection(cur, pts))(torch.zeros(free, dtype=torch.float64))  # [P 2 free]
        g_row, g_col = image_gradient(img)
        c = img.shape[-1]
        j = -(g_row.reshape(-1, c, 1) * dp[:, None, 0, :] + g_col.reshape(-1, c, 1) * dp[:, None, 1, :])
        j = j.reshape(-1, free)
        wr = cauchy_weights(r0, robust).reshape(-1)
        rr = r0.reshape(-1)
        a = (j * wr[:, None]).T @ j
        g = (j * wr[:, None]).T @ rr
        c0 = float((wr * rr**2).mean())
        accepted = False
        for _ in range(5):
            step = torch.linalg.solve(a + lam * torch.diag(torch.diag(a).clamp_min(1e-12)), g)
            cand = moved_camera(cur, step.float(), dist)
            out1, img1, r1 = look(cand)
            c1 = float((wr * r1.reshape(-1) ** 2).mean())
            if c1 < c0:
                base = cur
                cur, out, img, r0 = cand, out1, img1, r1
                lam = max(lam / 4.0, 1e-7)
                accepted = True
                scale = 2
                while scale <= extend:  # along a valley the step falls short: double it while that pays
                    cand = moved_camera(base, step.float() * scale, dist)
                    out2, img2, r2 = look(cand)
                    c2 = float((wr * r2.reshape(-1) ** 2).mean())
                    if c2 >= c1:
                        break
                    cur, out, img, r0, c1 = cand, out2, img2, r2, c2
                    scale *= 2
                break
            lam *= 8.0
        if not accepted or float(step.abs().max()) < 1e-6:
            break
    return cur, trimmed_rms(r0, trim), it


def sample_at(img: Float[Tensor, "H W C"], pixels: Float[Tensor, "P 2"]) -> Tuple[Tensor, Tensor]:
    """``img`` bilinearly sampled at continuous ``pixels`` (row, column; pixel centres at ``i + 0.5``, as
    :func:`pixel_grid`), and which of them fall inside the image. Returns ``([P C], [P])``."""
    h, w = img.shape[:2]
    x = 2.0 * pixels[:, 1] / w - 1.0
    y = 2.0 * pixels[:, 0] / h - 1.0
    grid = torch.stack([x, y], dim=-1).to(img.dtype)[None, None]
    out = F.grid_sample(img.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    inside = (pixels[:, 0] >= 0.5) & (pixels[:, 0] <= h - 0.5) & (pixels[:, 1] >= 0.5) & (pixels[:, 1] <= w - 0.5)
    return out[0, :, 0].T, inside


def warp_refine(
    model,
    camera: Cameras,
    target: Float[Tensor, "H W C"],
    value: bool,
    iterations: int,
    sigma: float = 0.0,
    renders: int = 2,
    robust: bool = True,
    trim: float = 1.0,
    free: int = POSE,
    render_blur: float = 0.0,
    renderer: Optional[Renderer] = None,
) -> Tuple[Cameras, float, int]:
    """Gauss-Newton over the ``free`` parameters of ``camera`` (:func:`lk_refine`; sized like ``target``) with the
    base render held fixed (made by ``renderer``, :func:`render_cameras` by default):
    the surface points the base shows at the camera (one render's depth) are projected through the moved pose into
    ``target``, which is sampled there; the residual ``target(pi(T P)) - render(p)`` and its Jacobian
    ``grad target * d pi / d pose`` need no render, so a step costs a projection and a bilinear sample. The base is
    rendered again at the pose reached, ``renders`` times in all (occlusions and the view-dependent colour change with
    the pose). Image and render are blurred by ``sigma`` px, the render by ``render_blur`` px more (:func:`lk_refine`).
    Returns the camera, the last residual's RMS (over the
    ``trim`` share of pixels with the smallest residuals) and the iterations taken.

    Examples:
        >>> cam, rms, its = warp_refine(model, camera, image, value=False, iterations=6, sigma=1.5)  # doctest: +SKIP
    """
    dist = camera_distance(camera)
    y = smoothed(target.double(), sigma)
    g_row, g_col = image_gradient(y)
    stacked = torch.cat([y, g_row, g_col], dim=-1)
    c = y.shape[-1]
    cur, rms, total = camera, float("nan"), 0

    for _ in range(max(1, renders)):
        out = (renderer or render_cameras)(model, cur, ("rgb", "expected_depth", "accumulation"))
        ref = smoothed(channel_of(out["rgb"][0], value).double(), math.hypot(sigma, render_blur)).reshape(-1, c)
        pixels = projection(cur, surface_points(cur, out["expected_depth"][0], out["accumulation"][0]))

        def residual(delta: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
            sampled, inside = sample_at(stacked, pixels(delta))
            return sampled[:, :c] - ref, sampled[:, c:], inside

        delta = torch.zeros(free, dtype=torch.float64)
        r0, grads, inside = residual(delta)
        lam = 1e-4
        for _ in range(iterations):
            dp = torch.func.jacfwd(pixels)(delta)  # [P 2 6]
            j = grads[:, :c, None] * dp[:, None, 0, :] + grads[:, c:, None] * dp[:, None, 1, :]  # [P C 6]
            wr = (cauchy_weights(r0, robust) * inside[:, None]).reshape(-1)
            j, rr = j.reshape(-1, free), r0.reshape(-1)
            a = (j * wr[:, None]).T @ j
            g = (j * wr[:, None]).T @ rr
            c0 = float((wr * rr**2).sum() / wr.sum().clamp_min(1e-12))
            accepted = False
            for _ in range(5):
                step = -torch.linalg.solve(a + lam * torch.diag(torch.diag(a).clamp_min(1e-12)), g)
                r1, grads1, inside1 = residual(delta + step)
                w1 = wr * inside1.repeat_interleave(c).double()
                c1 = float((w1 * r1.reshape(-1) ** 2).sum() / w1.sum().clamp_min(1e-12))
                if c1 < c0:
                    delta, r0, grads, inside = delta + step, r1, grads1, inside1
                    lam = max(lam / 4.0, 1e-7)
                    accepted = True
                    break
                lam *= 8.0
            total += 1
            if not accepted or float(step.abs().max()) < 1e-7:
                break
        rms = trimmed_rms(r0[inside], trim)
        if float(delta.abs().max()) < 1e-7:
            break
        cur = moved_camera(cur, delta.float(), dist)
    return cur, rms, total


def trimmed_rms(residual: Tensor, share: float = 1.0) -> float:
    """RMS over the ``share`` of the entries with the smallest magnitude (1: the plain RMS)."""
    sq = residual.reshape(-1) ** 2
    if share < 1.0:
        sq = torch.sort(sq).values[: max(1, int(round(share * sq.numel())))]
    return float(sq.mean().sqrt())


def line_search(
    model,
    camera: Cameras,
    step: Float[Tensor, " 6"],
    target: Float[Tensor, "H W C"],
    value: bool,
    sigma: float,
    max_scale: int = 8,
) -> Tuple[Cameras, int]:
    """``camera`` moved by ``step`` times the scale in 0, 1, 2, 4, ... ``max_scale`` (tried upward until the residual
    rises) whose base render (blurred by ``sigma`` px, on the content window) is nearest ``target`` (sized like the
    camera)."""
    dist = camera_distance(camera)
    full = render_cameras(model, camera, ("rgb", "accumulation"))
    window = content_window(full["accumulation"][0], int(3 * sigma) + 6)
    r0, r1, c0, c1 = window
    y = smoothed(target.double(), sigma)[r0:r1, c0:c1]

    def cost(out: Tensor) -> float:
        return float(((y - smoothed(channel_of(out, value).double(), sigma)) ** 2).mean())

    best, best_cost, best_scale = camera, cost(full["rgb"][0][r0:r1, c0:c1]), 0
    scale = 1
    while scale <= max_scale:
        cand = moved_camera(camera, step * scale, dist)
        c = cost(render_cameras(model, cand, ("rgb",), window)["rgb"][0])
        if c >= best_cost:
            break
        best, best_cost, best_scale = cand, c, scale
        scale *= 2
    return best, best_scale


def candidate_cameras(reference, count: int, seed: int) -> Cameras:
    """Candidate poses for the search: the base's training cameras and ``count`` novel ones drawn like the pool's
    (:func:`gsticker_plugin.fastpath.novel_cameras`)."""
    train = reference.pipeline.datamanager.train_dataset.cameras
    gen = torch.Generator().manual_seed(seed)
    c2w = [train.camera_to_worlds.float()]
    if count > 0:
        c2w.append(novel_cameras(train, count, gen).camera_to_worlds.float())
    c2w_all = torch.cat(c2w)
    n = c2w_all.shape[0]

    def first(x: Tensor) -> Tensor:
        return x[:1].expand(n, *x.shape[1:]).clone()

    return Cameras(
        camera_to_worlds=c2w_all,
        fx=first(train.fx),
        fy=first(train.fy),
        cx=first(train.cx),
        cy=first(train.cy),
        width=first(train.width),
        height=first(train.height),
        camera_type=first(train.camera_type),
    )


@dataclass
class PoseSearch:
    """Settings of :func:`estimate_camera`."""

    candidates: int = 700
    """Novel candidate poses besides the base's training cameras."""
    search_side: int = 16
    """Side (px) at which candidates are scored."""
    keep: int = 3
    """Best candidates refined."""
    trim: float = 0.75
    """The kept candidates' first stages are compared by the RMS of this share of the pixels with the smallest
    residuals: a part of the image painted over (cropout) cannot choose the candidate."""
    rolls: Sequence[float] = (0.0,)
    """Turns of the image about its centre (degrees) tried with every candidate: a camera rolled about its axis, or
    an image rotated after rendering (e.g. ``(-30, -20, -10, 0, 10, 20, 30)``)."""
    blurs: Sequence[float] = (6.0, 3.0, 1.5, 0.75)
    """Gaussian blur of the refinement stages, coarse to fine, in px per 100 px of the image's larger side."""
    iterations: Sequence[int] = (6, 6, 6, 6)
    """Gauss-Newton iterations per stage (the best candidate)."""
    first_iterations: int = 3
    """Iterations of the first stage for every kept candidate, before the best one goes on."""
    map_iterations: int = 3
    """Iterations per stage of a recoloured picture's search again through a colour map of the base's samples
    (:func:`gsticker_plugin.decoders.fieldimage.recoloured_camera`)."""
    half_size_blur: float = 1.5
    """Stages blurred by at least twice this many px run at half the image's size."""
    extend: int = 8
    """An accepted Gauss-Newton step is tried at up to this many times its length (:func:`lk_refine`)."""
    refine: Literal["auto", "render", "warp", "mixed"] = "auto"
    """How a stage steps: ``render`` (:func:`lk_refine`, a render per step), ``warp`` (:func:`warp_refine`, the image
    warped onto a held render, ``warp_renders`` renders per stage), ``mixed`` (``warp`` for every stage but the
    finest, which renders per step) or ``auto`` (the default: ``warp`` for pictures of more than ``warp_pixels``
    pixels, ``render`` for smaller ones, where a render is cheap and the warp samples few pixels through a depth that
    a half-transparent base does not give). docs/experiments/bench-pose-refine.md measures them."""
    warp_pixels: int = 64 * 64
    """``auto``: pictures of at most this many pixels are refined with a render per step."""
    warp_renders: int = 2
    """Renders per warped stage (``refine`` ``warp`` or ``mixed``)."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.refine not in ("auto", "render", "warp", "mixed"):
            raise ValueError(f"PoseSearch.refine must be auto, render, warp or mixed, got {self.refine!r}")

    def for_size(self, h: int, w: int) -> "PoseSearch":
        """This search with ``auto`` resolved for an ``h`` x ``w`` picture (``warp`` above :attr:`warp_pixels`)."""
        if self.refine != "auto":
            return self
        return replace(self, refine="warp" if h * w > self.warp_pixels else "render")


def estimate_camera(
    reference,
    image: Float[Tensor, "H W 3"],
    value: bool,
    search: PoseSearch = PoseSearch(),
    renders: Optional[Tuple[Cameras, Tensor]] = None,
) -> PoseFit:
    """The camera of ``image`` (a picture of the owner's scene at an unknown pose, the base's intrinsics scaled to
    its size) found against the owner's base ``reference`` (:func:`gsticker_plugin.decoders.reference.load_base_reference`).
    ``value``: compare V = max(R, G, B) (a hue-shifted image). ``renders``: the candidates and their renders at the
    search size, from :func:`search_renders` (computed once for many images)."""
    model = reference.model
    h, w = int(image.shape[0]), int(image.shape[1])
    train = reference.pipeline.datamanager.train_dataset.cameras
    w0, h0 = float(train.width[0]), float(train.height[0])
    if not same_aspect(w, h, w0, h0):
        raise GStickerError(
            f"a {w}x{h} image for a base whose cameras are {int(w0)}x{int(h0)} px (another aspect ratio): "
            "crop or pad it back to the base's frame, or pass --cameras"
        )
    sh = search.search_side
    sw = max(1, round(sh * w / h))
    cands, rows = renders if renders is not None else search_renders(reference, search, (h, w), value)
    # the image turned back by each roll: a rolled camera's picture is the candidate's turned about the centre
    turned = [
        image.float() if roll == 0 else rotate(image.float().permute(2, 0, 1)[None], -roll)[0].permute(1, 2, 0)
        for roll in search.rolls
    ]
    scores = torch.stack([ncc(rows, channel_of(area_resize(t, sh, sw), value).reshape(-1)) for t in turned], dim=1)
    flat = torch.argsort(scores.reshape(-1), descending=True)[: search.keep]
    best = [(int(i) // len(search.rolls), float(search.rolls[int(i) % len(search.rolls)])) for i in flat]

    def start(b: int, roll: float) -> Cameras:
        cam = scaled_camera(cands[b : b + 1], h, w)
        if roll == 0:
            return cam
        return moved_camera(cam, torch.tensor([0.0, 0.0, -math.radians(roll), 0.0, 0.0, 0.0]))

    b, cam, rms, total, history = refine_starts(model, image, [(b, start(b, roll)) for b, roll in best], value, search)
    return PoseFit(camera=cam, rms=rms, score=float(scores[b].max()), iterations=total, history=history)


def refine_starts(
    model,
    image: Float[Tensor, "H W 3"],
    starts: Sequence[Tuple[int, Cameras]],
    value: bool,
    search: PoseSearch,
    free: int = POSE,
    render_blur: float = 0.0,
    stages: Optional[int] = None,
) -> Tuple[int, Cameras, float, int, List[Dict[str, Any]]]:
    """The refinement of :func:`estimate_camera` from the start cameras ``(candidate, camera)`` (sized like
    ``image``): the first stage for each (RMS over :attr:`PoseSearch.trim` of the pixels), then every stage (the first
    ``stages`` of them; :func:`refine_further` runs the rest) for the one that explains the image best; ``free``: the
    parameters moved, ``render_blur``: px the image was blurred after rendering (:func:`refine_stage`). Returns its
    candidate, camera, RMS, the iterations taken and the stages' history."""
    search = search.for_size(int(image.shape[0]), int(image.shape[1]))
    history: List[Dict[str, Any]] = []
    first = []
    for b, start in starts:
        cam, rms, n_it = refine_stage(
            model,
            image,
            start,
            value,
            search,
            search.blurs[0],
            search.first_iterations,
            render_blur=render_blur,
            trim=search.trim,
            free=free,
        )
        history.append({"candidate": b, **record(cam, rms, n_it, search.blurs[0])})
        first.append((b, cam, rms, n_it))
    b, cam, rms, total = min(first, key=lambda f: f[2])
    cam, rms, n_it, more = refine_further(model, image, cam, value, search, 0, stages, free, render_blur)
    history += [{"candidate": b, **h} for h in more]
    return b, cam, rms, total + n_it, history


def refine_further(
    model,
    image: Float[Tensor, "H W 3"],
    camera: Cameras,
    value: bool,
    search: PoseSearch,
    begin: int = 0,
    end: Optional[int] = None,
    free: int = POSE,
    render_blur: float = 0.0,
) -> Tuple[Cameras, float, int, List[Dict[str, Any]]]:
    """Stages ``begin`` to ``end`` of ``search`` (:func:`refine_stage`; the finest renders per step when
    ``search.refine`` is ``mixed``) from ``camera``. Returns the camera, the last stage's RMS, the iterations taken and
    the stages' history."""
    search = search.for_size(int(image.shape[0]), int(image.shape[1]))
    history: List[Dict[str, Any]] = []
    cam, rms, total = camera, float("nan"), 0
    n = min(len(search.blurs), len(search.iterations))
    for i in range(begin, n if end is None else min(end, n)):
        blur, its = search.blurs[i], search.iterations[i]
        stage = replace(search, refine="render") if search.refine == "mixed" and i == n - 1 else search
        cam, rms, n_it = refine_stage(model, image, cam, value, stage, blur, its, render_blur, free=free)
        history.append(record(cam, rms, n_it, blur))
        total += n_it
    return cam, rms, total, history


def record(cam: Cameras, rms: float, iterations: int, blur: float) -> Dict[str, Any]:
    """A refinement stage's entry of :attr:`PoseFit.history`."""
    return {"blur": blur, "rms": rms, "iterations": iterations, "c2w": cam.camera_to_worlds[0].tolist()}


def refine_stage(
    model,
    image: Float[Tensor, "H W 3"],
    camera: Cameras,
    value: bool,
    search: PoseSearch,
    blur: float,
    iterations: int,
    render_blur: float = 0.0,
    trim: float = 1.0,
    free: int = POSE,
) -> Tuple[Cameras, float, int]:
    """One coarse-to-fine stage of :func:`estimate_camera`: :func:`lk_refine` (or :func:`warp_refine` where
    ``search.refine`` says so; ``auto``, resolved by :func:`refine_starts`, steps as ``render`` here) of ``camera``
    against ``image`` (V with ``value``) at ``blur`` px per 100 px of its larger side; stages blurred by at least twice
    :attr:`PoseSearch.half_size_blur` run at half size; ``render_blur``: px (at the image's size) the image was
    blurred after rendering; ``trim``: the RMS's share of pixels and ``free`` the parameters moved
    (:func:`lk_refine`). Returns the camera at the image's size, the RMS and the iterations taken."""
    h, w = int(image.shape[0]), int(image.shape[1])
    sigma = blur * max(h, w) / 100.0
    # blurred stages run at half size (the blur has removed what the finer pixels would add)
    f = 2 if sigma >= 2 * search.half_size_blur else 1
    lh, lw = max(1, h // f), max(1, w // f)
    target = channel_of(image.float() if f == 1 else area_resize(image, lh, lw), value)
    if search.refine in ("warp", "mixed"):
        start = scaled_camera(camera, lh, lw)
        sig, rb = sigma / f, render_blur / f
        cam, rms, n_it = warp_refine(
            model, start, target, value, iterations, sig, search.warp_renders, trim=trim, free=free, render_blur=rb
        )
        return scaled_camera(cam, h, w), rms, n_it
    cam, rms, n_it = lk_refine(
        model,
        scaled_camera(camera, lh, lw),
        target,
        value,
        iterations,
        sigma / f,
        extend=search.extend,
        render_blur=render_blur / f,
        trim=trim,
        free=free,
    )
    return scaled_camera(cam, h, w), rms, n_it


def search_renders(
    reference, search: PoseSearch, hw: Tuple[int, int], value: bool, bank: Optional[Path] = None
) -> Tuple[Cameras, Tensor]:
    """Candidates and their base renders at the search size for images of ``hw`` (only its aspect ratio matters):
    the candidates' intrinsics scaled to the search frame. ``bank``: the owner key's view bank folder
    (:mod:`gsticker_plugin.decoders.viewbank`), read when it holds these renders and written when it does not."""
    h, w = hw
    cands = candidate_cameras(reference, search.candidates, search.seed)
    sh = search.search_side
    sw = max(1, round(sh * w / h))
    path = None
    if bank is not None:
        name = VB.bank_name(
            reference.checkpoint,
            reference.config_path,
            type(reference.model).__qualname__,
            search.candidates,
            search.seed,
            sh,
            sw,
        )
        path = bank / f"{name}.pt"
    rgb = VB.load_bank(path, len(cands), sh, sw) if path is not None else None
    if rgb is None:
        sx, sy = sw / float(cands.width[0]), sh / float(cands.height[0])
        small = Cameras(
            camera_to_worlds=cands.camera_to_worlds,
            fx=cands.fx * sx,
            fy=cands.fy * sy,
            cx=cands.cx * sx,
            cy=cands.cy * sy,
            width=torch.full_like(cands.width, sw),
            height=torch.full_like(cands.height, sh),
            camera_type=cands.camera_type,
        )
        rgb = render_cameras(reference.model, small)["rgb"].float().cpu()
        if path is not None:
            VB.save_bank(path, rgb)
    return cands, channel_of(rgb, value).reshape(rgb.shape[0], -1)


def render_at(model, camera: Cameras, rays: Int[Tensor, " R"]) -> Float[Tensor, "R 3"]:
    """The model's colour at the flat pixel indices ``rays`` of one camera, on the CPU (``[0 3]`` for no rays)."""
    if rays.numel() == 0:
        return torch.zeros(0, 3)
    out = render_rays(model, camera, rays)["rgb"].reshape(-1, 3)[rays.to(model.device)]
    return out.float().cpu()


def flow_columns(
    camera: Cameras,
    rgb: Float[Tensor, "H W 3"],
    depth: Float[Tensor, "H W 1"],
    accumulation: Float[Tensor, "H W 1"],
    rays: Int[Tensor, " R"],
    value: bool,
    free: int = POSE,
) -> Float[Tensor, "M free"]:
    """d (base render at ``rays``) / d (pose, and with ``free`` = :data:`FRAMED` zoom and principal point, as
    :func:`moved_camera`) from one render of ``camera`` (its colour, depth and accumulation): the point each pixel
    sees moves to ``pi(delta)`` (:func:`projection`), so the render there changes by ``-grad(render) . d pi / d
    delta`` (central differences of the render, :func:`image_gradient`). What :func:`pose_columns` gives with a render a
    column, save for view-dependent colour and what a move uncovers. Rows ``r * 3 + c``, or one V row per ray with
    ``value``."""
    x = channel_of(rgb.float(), value)
    g_row, g_col = image_gradient(x)
    points = surface_points(camera, depth, accumulation).reshape(-1, 3)[rays.cpu()]
    dp = torch.func.jacfwd(projection(camera, points))(torch.zeros(free, dtype=torch.float64))  # [R 2 free]
    c = x.shape[-1]
    gr, gc = g_row.reshape(-1, c)[rays.cpu()], g_col.reshape(-1, c)[rays.cpu()]
    cols = -(gr[:, :, None] * dp[:, None, 0, :] + gc[:, :, None] * dp[:, None, 1, :])  # [R C free]
    return cols.reshape(-1, free).float()


def pose_columns(
    model,
    camera: Cameras,
    rays: Int[Tensor, " R"],
    value: bool,
    eps: float = 3.5e-4,
    free: int = POSE,
    base: Optional[Float[Tensor, "R 3"]] = None,
) -> Float[Tensor, "M free"]:
    """d (base render at ``rays``) / d (pose, and with ``free`` = :data:`FRAMED` zoom and principal point, as
    :func:`moved_camera`) by finite differences (rows ``r * 3 + c``, or one V row per ray with ``value``): what the
    image decoder fits beside the message for a camera this module estimated. Steps: ``eps`` for the pose and the log
    zoom, :data:`PRINCIPAL_STEP` px for the principal point. Central differences (two renders a column), or forward
    ones from ``base`` (the base's RGB at ``rays`` and ``camera``, already rendered: one render a column)."""
    dist = camera_distance(camera)
    at = None if base is None else channel_of(base.float().cpu(), value)

    cols = []
    for k in range(free):
        e = torch.zeros(free)
        e[k] = PRINCIPAL_STEP if k >= 7 else eps
        plus = channel_of(render_at(model, moved_camera(camera, e, dist), rays), value)
        if at is not None:
            cols.append(((plus - at) / float(e[k])).reshape(-1))
            continue
        minus = channel_of(render_at(model, moved_camera(camera, -e, dist), rays), value)
        cols.append(((plus - minus) / (2 * float(e[k]))).reshape(-1))
    return torch.stack(cols, dim=1)
