"""The camera of a picture framed in any way: another aspect ratio, zoomed, cropped, letterboxed or resized.

A picture re-posted from a render is the render at some camera seen through a framing
(:mod:`gsticker_plugin.decoders.framing`): zoom ``s``, offset ``t``, size ``W' x H'``. It is itself the picture of
a pinhole camera with the same pose and the intrinsics ::

    fx' = s fx,   fy' = s fy,   cx' = s cx + tx,   cy' = s cy + ty,   size W' x H'.

:func:`estimate_framed_camera` finds that camera against the owner's base:

1. uniform bars along the picture's edges (letterboxing, padding) are cut off by the caller (:func:`content_box`);
2. each search candidate's render (the view bank of :func:`gsticker_plugin.decoders.pose.search_renders`) is framed
   against the picture by normalized cross-correlation over zooms and offsets
   (:func:`gsticker_plugin.decoders.framing.coarse_framings`);
3. the picture is worked at no more than the base's own scale (a larger copy averaged down: it holds nothing the
   base's render did not), and a resized copy is compared with renders blurred by :data:`RESAMPLED_BLUR` (what its
   resampling blurred);
4. the best candidates' cameras, framed like the picture (:func:`framed_camera`), are refined on the picture by the
   first :data:`RENDERED_STAGES` pose stages of :func:`gsticker_plugin.decoders.pose.estimate_camera`
   (:func:`gsticker_plugin.decoders.pose.refine_starts`);
5. a picture then zoomed by more than :data:`RESAMPLED` is refined again on the whole picture as a resized copy is
   made - the base rendered at its own intrinsics over the picture's :func:`footprint` and resized with the filter
   that matches - and its render's pixel grid put back where the copy's lay (:func:`refine_resampled`,
   :func:`phase_fit`); that camera is kept when it explains the picture better than the one of step 4 (a render at
   the picture's own intrinsics), whose remaining stages run otherwise.

A framing's error left after step 2 is a fraction of a coarse pixel; the pose moves to absorb it (a zoom error as a
step along the axis, an offset as a turn), which is what a camera of the right pose would show up to the scene's
parallax at that scale. Uses the picture and the owner's base only, never the owner's message.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from gsticker_plugin.decoders.framing import Framing, coarse_framings
from gsticker_plugin.decoders.pose import (
    FRAMED,
    POSE,
    PoseFit,
    PoseSearch,
    Renderer,
    Window,
    camera_distance,
    channel_of,
    moved_camera,
    refine_further,
    refine_starts,
    render_cameras,
    scaled_camera,
    search_renders,
    warp_refine,
)
from gsticker_plugin.fastpath import axis_angle_matrix, smoothed

PICTURE_SCALES = tuple(float(z) for z in torch.logspace(math.log10(0.3), math.log10(4.5), 29).tolist())
"""Picture px per base px tried by the coarse framing: a copy 0.5 to 3 times the base's size, zoomed 0.7 to 1.5
times (10 % apart)."""
COARSE_SIDE = 24
"""Larger side (px) at which picture and candidates are correlated for the coarse framing."""
RESAMPLED = 0.03
"""A picture zoomed by more than this share against the base's render is taken for a resized copy."""
RESAMPLED_BLUR = 0.45
"""Blur (px of the picture worked) a resized copy holds beyond a render (the resampling kernels'), put on the
renders it is compared with."""
RESAMPLED_STAGES = ((3.0, 1.5, 0.75), (0.75, 0.4))
"""Blurs (px per 100 px of the picture's larger side) of :func:`refine_resampled`'s groups of stages."""
RENDERED_STAGES = 2
"""Stages of the search (:attr:`gsticker_plugin.decoders.pose.PoseSearch.blurs`) a framed picture runs on renders at
its own intrinsics before its zoom decides whether it is taken for a resized copy (:func:`refine_resampled`); the rest
run unless the copy's model explains it better."""
RESAMPLED_RENDERS = 2
"""Renders of the base per stage of :func:`refine_resampled` (:func:`gsticker_plugin.decoders.pose.warp_refine`)."""
RESAMPLED_HALF = 3.0
"""Stages of :func:`refine_resampled` blurred by at least this many px per 100 px render the base at half its size."""
PHASE_SUPERSAMPLE = 2
"""How many times finer than the base :func:`phase_fit` renders (its candidates sample that render)."""
PHASE_REACH = 3.0
"""Base px a :func:`phase_fit` may move the camera's render (a turn, the framing's offset)."""
FOOTPRINT_MARGIN = 4.0
"""Base px around a picture's footprint in the base frame that a resized copy's renders cover (:func:`footprint`):
room for the refinement's moves."""
BAR_TOLERANCE = 6.0 / 255.0
"""A row or column whose values span less than this in every channel is a bar."""


def content_box(picture: Float[Tensor, "H W 3"], tolerance: float = BAR_TOLERANCE, min_side: int = 8) -> Window:
    """The picture less uniform bars along its edges (each a single colour, rows or columns whose values span less
    than ``tolerance``): rows ``[r0, r1)`` and columns ``[c0, c1)``; at least ``min_side`` px a side.

    Examples:
        >>> import torch
        >>> p = torch.zeros(10, 20, 3); p[:, 5:15] = torch.rand(10, 10, 3)
        >>> content_box(p, min_side=2)
        (0, 10, 5, 15)
    """
    x = picture.float()
    flat_rows = (x.amax(dim=1) - x.amin(dim=1)).amax(dim=-1) < tolerance  # [H]
    flat_cols = (x.amax(dim=0) - x.amin(dim=0)).amax(dim=-1) < tolerance  # [W]

    def span(flat: Tensor) -> Tuple[int, int]:
        n = flat.numel()
        keep = torch.nonzero(~flat).reshape(-1)
        if keep.numel() == 0:
            return 0, n
        a, b = int(keep[0]), int(keep[-1]) + 1
        if b - a < min_side:
            grow = min_side - (b - a)
            a = max(0, a - (grow + 1) // 2)
            b = min(n, a + max(min_side, b - a))
            a = max(0, b - min_side)
        return a, b

    r0, r1 = span(flat_rows)
    c0, c1 = span(flat_cols)
    return r0, r1, c0, c1


def framed_camera(camera: Cameras, framing: Framing, height: int, width: int, c2w: Optional[Tensor] = None) -> Cameras:
    """The one-camera ``camera`` (a render's intrinsics) framed like a picture: ``height x width`` px with
    :meth:`gsticker_plugin.decoders.framing.Framing.intrinsics`, the same pose (or ``c2w``, ``[1 3 4]``)."""
    fx, fy, cx, cy = framing.intrinsics(
        *(float(x.reshape(-1)[0]) for x in (camera.fx, camera.fy, camera.cx, camera.cy))
    )

    def one(x: float) -> Tensor:
        return torch.full((1, 1), x)

    return Cameras(
        camera_to_worlds=camera.camera_to_worlds[:1].detach().float().cpu() if c2w is None else c2w,
        fx=one(fx),
        fy=one(fy),
        cx=one(cx),
        cy=one(cy),
        width=int(width),
        height=int(height),
        camera_type=camera.camera_type[:1].cpu(),
    )


def estimate_framed_camera(
    reference,
    picture: Float[Tensor, "H W 3"],
    value: bool,
    search: PoseSearch = PoseSearch(),
    renders: Optional[Tuple[Cameras, Tensor]] = None,
) -> PoseFit:
    """The camera of ``picture`` (any size and aspect ratio, its bars already cut: :func:`content_box`) found against
    the owner's base (see the module's docstring). ``value``: compare V = max(R, G, B). ``renders``:
    :func:`gsticker_plugin.decoders.pose.search_renders` at the base's own size (computed once for many pictures).
    The fit's camera is sized like ``picture``."""
    train = reference.pipeline.datamanager.train_dataset.cameras
    h0, w0 = int(train.height[0]), int(train.width[0])
    cands, rows = renders if renders is not None else search_renders(reference, search, (h0, w0), value)
    sh = search.search_side
    sw = max(1, round(sh * w0 / h0))
    pic = picture.float()
    per_bank = sh / h0  # bank px per base px
    coarse = coarse_framings(
        channel_of(pic, value)[..., 0] if value else pic,
        rows.reshape(-1, sh, sw) if value else rows.reshape(-1, sh, sw, 3),
        [z / per_bank for z in PICTURE_SCALES],
        side=COARSE_SIDE,
    )
    order = sorted(range(len(coarse)), key=lambda i: -coarse[i].score)[: search.keep]
    framings: List[Framing] = []
    for b in order:
        c = coarse[b]
        framings.append(Framing(c.sx * per_bank, c.sy * per_bank, c.tx, c.ty, c.score))
    scale = max(1.0, framings[0].sx)  # picture px per base px of the best
    ph, pw = pic.shape[0], pic.shape[1]
    hh, ww = max(1, round(ph / scale)), max(1, round(pw / scale))
    work = pic if (hh, ww) == (ph, pw) else resized(pic, hh, ww)
    starts = [(b, scaled_camera(framed_camera(cands[b : b + 1], f, ph, pw), hh, ww)) for b, f in zip(order, framings)]
    blur = RESAMPLED_BLUR if resampled(framings[0].sx) else 0.0
    b, cam, rms, total, history = refine_starts(
        reference.model, work, starts, value, search, FRAMED, blur, RENDERED_STAGES
    )
    best = framings[order.index(b)]
    at = scaled_camera(cam, ph, pw)
    if resampled(framing_of(at, train[:1]).sx):  # a resized copy of a render, or a render at its own intrinsics
        again, kernel = refine_resampled(reference.model, train[:1], at, pic, value)
        as_resized = resampled_renderer(train[:1], kernel)(reference.model, again, ("rgb",))["rgb"][0]
        as_rendered = render_cameras(reference.model, at)["rgb"][0]
        if _rms(as_resized, pic, value) < _rms(as_rendered, pic, value):
            return PoseFit(again, rms, best.score, total, history, resampler=kernel)
    cam, rms, n_it, more = refine_further(
        reference.model, work, cam, value, search, RENDERED_STAGES, None, FRAMED, blur
    )
    history += [{"candidate": b, **h} for h in more]
    return PoseFit(scaled_camera(cam, ph, pw), rms, best.score, total + n_it, history)


def resampled(zoom: float) -> bool:
    """Whether a picture at ``zoom`` picture px per base px is taken for a resized copy (:data:`RESAMPLED`)."""
    return abs(math.log(zoom)) > math.log(1.0 + RESAMPLED)


def resized(image: Float[Tensor, "H W 3"], height: int, width: int) -> Float[Tensor, "h w 3"]:
    """``image`` resampled to ``height x width`` (antialiased bilinear: each axis scaled evenly, edges to edges)."""
    x = image.float().permute(2, 0, 1)[None]
    out = F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return out[0].permute(1, 2, 0).clamp(0, 1)


def framing_of(camera: Cameras, base: Cameras) -> Framing:
    """The framing that takes ``base``'s intrinsics (a render at the base's own size) to ``camera``'s (a picture's):
    ``sx = fx' / fx``, ``tx = cx' - sx cx`` (pixel edges), and likewise in y."""
    sx = float(camera.fx.reshape(-1)[0]) / float(base.fx.reshape(-1)[0])
    sy = float(camera.fy.reshape(-1)[0]) / float(base.fy.reshape(-1)[0])
    tx = float(camera.cx.reshape(-1)[0]) - sx * float(base.cx.reshape(-1)[0])
    ty = float(camera.cy.reshape(-1)[0]) - sy * float(base.cy.reshape(-1)[0])
    return Framing(sx, sy, tx, ty)


def base_frame(camera: Cameras, base: Cameras) -> Cameras:
    """``camera``'s pose with ``base``'s intrinsics and size (one camera)."""
    c2w = camera.camera_to_worlds[:1].detach().float().cpu()
    return framed_camera(base[:1], Framing(1.0, 1.0, 0.0, 0.0), int(base.height[0]), int(base.width[0]), c2w)


def footprint(camera: Cameras, base: Cameras, margin: float = FOOTPRINT_MARGIN) -> Cameras:
    """The part of ``base``'s frame that the framed ``camera``'s picture shows, widened by ``margin`` base px and by
    the reach of a resampling filter (3 taps, widened when the picture is smaller), within the frame: a camera at
    ``camera``'s pose with the base's focal length, its principal point moved by the part's corner and its size. A
    render there is the base frame's render cut to that part (every ray is the same)."""
    f = framing_of(camera, base)
    h0, w0 = int(base.height[0]), int(base.width[0])
    ph, pw = int(camera.height.reshape(-1)[0]), int(camera.width.reshape(-1)[0])
    reach = margin + 3.0 * max(1.0, 1.0 / min(f.sx, f.sy))
    c0 = max(0, math.floor(-f.tx / f.sx - reach))
    c1 = min(w0, math.ceil((pw - f.tx) / f.sx + reach))
    r0 = max(0, math.floor(-f.ty / f.sy - reach))
    r1 = min(h0, math.ceil((ph - f.ty) / f.sy + reach))
    if c1 <= c0 or r1 <= r0:
        c0, c1, r0, r1 = 0, w0, 0, h0
    part = Framing(1.0, 1.0, -float(c0), -float(r0))
    c2w = camera.camera_to_worlds[:1].detach().float().cpu()
    return framed_camera(base[:1], part, r1 - r0, c1 - c0, c2w)


def resampling_kernel(name: str, x: Tensor) -> Tensor:
    """A resampling filter at offsets ``x`` (input px): ``bilinear`` (triangle), ``bicubic`` (Keys, a = -0.5: Pillow's),
    ``cubic-0.75`` (Keys, a = -0.75: OpenCV's and torch's) or ``lanczos`` (3 lobes)."""
    ax = x.abs()
    if name == "bilinear":
        return (1.0 - ax).clamp_min(0.0)
    if name in ("bicubic", "cubic-0.75"):
        a = -0.5 if name == "bicubic" else -0.75
        near = ((a + 2.0) * ax - (a + 3.0)) * ax * ax + 1.0
        far = ((a * ax - 5.0 * a) * ax + 8.0 * a) * ax - 4.0 * a
        return torch.where(ax < 1.0, near, torch.where(ax < 2.0, far, torch.zeros_like(ax)))
    if name == "lanczos":
        return torch.where(ax < 3.0, torch.sinc(x) * torch.sinc(x / 3.0), torch.zeros_like(ax))
    raise ValueError(f"unknown resampling kernel {name!r}")


RESAMPLERS = ("bicubic", "cubic-0.75", "bilinear", "lanczos")
"""The resampling filters a resized copy is matched against (:func:`read_framed`'s choice): what common image tools
resize with."""


def resampling_matrix(n_out: int, n_in: int, scale: float, offset: float, kernel: str) -> Float[Tensor, "O I"]:
    """Separable resampling as Pillow does it: output pixel ``u`` takes the input around ``(u + 0.5 - offset) /
    scale`` (edge coordinates) through ``kernel``, widened by ``1 / scale`` when shrinking (antialiased); its taps
    inside the input sum to one."""
    centre = (torch.arange(n_out, dtype=torch.float64) + 0.5 - offset) / scale
    widen = max(1.0 / scale, 1.0)
    taps = torch.arange(n_in, dtype=torch.float64) + 0.5
    w = resampling_kernel(kernel, (taps[None, :] - centre[:, None]) / widen)
    total = w.sum(dim=1, keepdim=True)
    return torch.where(total.abs() > 1e-12, w / total, torch.zeros_like(w)).float()


def warp_to_picture(
    stack: Float[Tensor, "C h w"], framing: Framing, height: int, width: int, kernel: Optional[str] = None
) -> Tuple[Float[Tensor, "C H W"], Tensor]:
    """Base-frame images (any channels) as the framed picture shows them, ``height x width``: through ``kernel``
    (:func:`resampling_matrix`, one of :data:`RESAMPLERS`), or by default enlarged by bicubic interpolation and
    shrunk by a Gaussian of the shrink's width then bilinear interpolation; and which of the picture's pixels the
    base frame covers."""
    h0, w0 = stack.shape[-2:]
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij"
    )
    ub = (u + 0.5 - framing.tx) / framing.sx  # base-frame coordinates (pixel edges) of the picture's pixel centres
    vb = (v + 0.5 - framing.ty) / framing.sy
    inside = (ub >= 0.5) & (ub <= w0 - 0.5) & (vb >= 0.5) & (vb <= h0 - 0.5)
    if kernel is not None:
        wy = resampling_matrix(height, h0, framing.sy, framing.ty, kernel)
        wx = resampling_matrix(width, w0, framing.sx, framing.tx, kernel)
        return torch.einsum("Hh,chw,Ww->cHW", wy, stack.float(), wx), inside
    s = min(framing.sx, framing.sy)
    img = stack.float()
    if s < 1:
        img = smoothed(img.permute(1, 2, 0), 0.5 * math.sqrt(1 / (s * s) - 1)).permute(2, 0, 1)
    img = img[None]
    grid = torch.stack([ub / w0 * 2 - 1, vb / h0 * 2 - 1], dim=-1)[None]
    mode = "bicubic" if s > 1 else "bilinear"
    out = F.grid_sample(img, grid, mode=mode, padding_mode="border", align_corners=False)[0]
    return out, inside


def matched_resampler(render: Float[Tensor, "h w 3"], picture: Float[Tensor, "H W 3"], framing: Framing) -> str:
    """The resampling filter (:data:`RESAMPLERS`) whose resize of the base's ``render`` by ``framing`` is nearest
    ``picture`` where the render covers it: the tool a resized copy was made with. Uses the picture and the base
    only."""
    ph, pw = int(picture.shape[0]), int(picture.shape[1])
    costs = {}
    for kernel in RESAMPLERS:
        warped, inside = warp_to_picture(render.permute(2, 0, 1), framing, ph, pw, kernel)
        costs[kernel] = float(((warped.permute(1, 2, 0) - picture.float())[inside] ** 2).mean())
    return min(costs, key=costs.__getitem__)


def resampled_renderer(base: Cameras, kernel: str) -> Renderer:
    """A :data:`gsticker_plugin.decoders.pose.Renderer` for a framed camera that renders it as a resized copy was
    made: the base at its own intrinsics and the camera's pose (:func:`base_frame`), carried into the picture by the
    camera's framing (:func:`warp_to_picture`; colour through ``kernel``, depth and accumulation bilinearly, the
    accumulation 0 where the base frame does not reach)."""

    def render(model, camera: Cameras, keys: Sequence[str] = ("rgb",)) -> Dict[str, Tensor]:
        part = footprint(camera, base)
        out = render_cameras(model, part, keys)
        framing = framing_of(camera, part)
        h, w = int(camera.height[0]), int(camera.width[0])
        framed = {}
        for k in keys:
            x, inside = warp_to_picture(out[k][0].permute(2, 0, 1), framing, h, w, kernel if k == "rgb" else "bilinear")
            framed[k] = (x * inside if k == "accumulation" else x).permute(1, 2, 0)[None]
        return framed

    return render


def phase_fit(
    model,
    base: Cameras,
    camera: Cameras,
    picture: Float[Tensor, "H W 3"],
    value: bool,
    kernel: str,
    supersample: int = PHASE_SUPERSAMPLE,
    iterations: int = 30,
) -> Cameras:
    """The framed ``camera`` of a resized copy moved to where the base render's pixel grid lies as it lay when the
    copy was made (see :func:`refine_resampled`): the base rendered once at ``camera``'s pose, ``supersample`` times
    finer (``R``); a candidate turns that camera by ``w`` (3), steps along its axis (``z``: the ray grid zoomed by
    ``e^z`` about the principal point) and frames by ``(log s, tx, ty)``; its render is ``R`` sampled at the
    candidate's pixel-centre rays (exact for a turn) and resized into the picture by ``kernel``. Levenberg-Marquardt
    on the picture's pixels (``V`` with ``value``) from turns a whole base px apart, -1 to 1 each way (a local minimum
    each, as far apart); the best goes on for ``iterations``. The step along the axis is the zoom at the base's
    median depth. A fit that leaves more than the camera as given, or moves beyond :data:`PHASE_REACH` base px (or
    5 % in zoom, 0.05 rad in roll), leaves it as given. Returns the camera, sized like ``picture``."""
    dist = camera_distance(camera)
    at = footprint(camera, base, FOOTPRINT_MARGIN + PHASE_REACH)
    frame0 = framing_of(camera, at)
    h0, w0 = int(at.height[0]), int(at.width[0])
    fine = scaled_camera(at, h0 * supersample, w0 * supersample)
    out = render_cameras(model, fine, ("rgb", "expected_depth", "accumulation"))
    big = channel_of(out["rgb"][0], value).permute(2, 0, 1)[None].float()
    solid = out["accumulation"][0, ..., 0] > 0.5
    depth = float(out["expected_depth"][0, ..., 0][solid].median()) if bool(solid.any()) else dist
    fx, fy, cx, cy = (float(x.reshape(-1)[0]) for x in (at.fx, at.fy, at.cx, at.cy))
    ph, pw = int(picture.shape[0]), int(picture.shape[1])
    target = channel_of(picture.float(), value)[..., 0] if value else picture.float().permute(2, 0, 1)
    ii, jj = torch.meshgrid(
        torch.arange(h0, dtype=torch.float64) + 0.5, torch.arange(w0, dtype=torch.float64) + 0.5, indexing="ij"
    )

    def framing(p: Tensor) -> Framing:
        s = math.exp(float(p[4]))
        return Framing(frame0.sx * s, frame0.sy * s, frame0.tx + float(p[5]), frame0.ty + float(p[6]))

    def residual(p: Tensor) -> Tensor:
        z = math.exp(float(p[3]))
        ray = torch.stack([(jj - cx) / (fx * z), -(ii - cy) / (fy * z), -torch.ones_like(ii)], dim=-1)
        angle = float(p[:3].norm())
        turn = axis_angle_matrix((p[:3] / angle).float(), angle).double() if angle > 0 else torch.eye(3).double()
        d = ray @ turn.T  # the candidate's rays in the rendered camera's frame
        col = cx + fx * d[..., 0] / (-d[..., 2])
        row = cy - fy * d[..., 1] / (-d[..., 2])
        grid = torch.stack([col / w0 * 2 - 1, row / h0 * 2 - 1], dim=-1)[None].float()
        img = F.grid_sample(big, grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
        warped, inside = warp_to_picture(img, framing(p), ph, pw, kernel)
        return ((warped[0] if value else warped) - target) * inside

    steps = torch.tensor([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 0.02, 0.02], dtype=torch.float64)
    starts = []
    for a in (-1, 0, 1):
        for b in (-1, 0, 1):
            p = torch.zeros(7, dtype=torch.float64)
            p[0], p[1] = b / fy, a / fx  # a turn about x moves the rows, about y the columns
            starts.append(least_squares(residual, p, steps, 3))
    p, rms = least_squares(residual, min(starts, key=lambda s: s[1])[0], steps, iterations)
    still = float(residual(torch.zeros(7, dtype=torch.float64)).pow(2).mean().sqrt())
    reach = torch.tensor(
        [PHASE_REACH / fy, PHASE_REACH / fx, 0.05, 0.05, 0.05, PHASE_REACH * frame0.sx, PHASE_REACH * frame0.sy]
    )
    if not (bool(torch.isfinite(p).all()) and bool((p.abs() <= reach.double()).all()) and rms < still):
        return camera  # a fit that ran off (or did not help) leaves the camera as it was
    delta = torch.zeros(POSE)
    delta[:3] = p[:3].float()
    delta[5] = -(math.exp(float(p[3])) - 1.0) * depth / dist  # forward is -z
    moved = moved_camera(at, delta, dist)
    return framed_camera(at, framing(p), ph, pw, moved.camera_to_worlds)


def least_squares(residual, p: Tensor, steps: Tensor, iterations: int) -> Tuple[Tensor, float]:
    """Levenberg-Marquardt on ``residual(p)`` (any shape) from ``p``, central-difference Jacobian with ``steps``;
    returns the parameters and the residual's RMS."""
    r = residual(p).reshape(-1).double()
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        cols = [
            (residual(p + e) - residual(p - e)).reshape(-1).double() / (2 * float(e.norm())) for e in torch.diag(steps)
        ]
        j = torch.stack(cols, dim=1)
        a, g = j.T @ j, j.T @ r
        accepted = False
        for _ in range(6):
            step = -torch.linalg.solve(a + lam * torch.diag(torch.diag(a).clamp_min(1e-12)), g)
            r1 = residual(p + step).reshape(-1).double()
            c1 = float(r1 @ r1)
            if c1 < cost:
                p, r, cost, lam, accepted = p + step, r1, c1, max(lam / 4, 1e-7), True
                break
            lam *= 8
        if not accepted:
            break
    return p, math.sqrt(cost / max(1, r.numel()))


def _rms(render: Float[Tensor, "H W 3"], picture: Float[Tensor, "H W 3"], value: bool) -> float:
    return float((channel_of(render, value) - channel_of(picture.float(), value)).pow(2).mean().sqrt())


def refine_resampled(
    model,
    base: Cameras,
    camera: Cameras,
    picture: Float[Tensor, "H W 3"],
    value: bool,
    last: bool = False,
) -> Tuple[Cameras, str]:
    """The framed ``camera`` of a resized copy refined on the whole ``picture`` as it was made: the base rendered at
    its own intrinsics and resized like the picture with the matched filter (:func:`matched_resampler`,
    :func:`resampled_renderer`), by :func:`gsticker_plugin.decoders.pose.warp_refine` over the pose, zoom and principal
    point at the blurs of :data:`RESAMPLED_STAGES` (its ``last`` group alone for a camera already refined so;
    :data:`RESAMPLED_RENDERS` renders each, at half the base's size from :data:`RESAMPLED_HALF`), each group followed
    by :func:`phase_fit`.

    A render's colours are the field's at its pixel-centre rays, and a resized copy keeps where those rays fell:
    a camera turned by a whole pixel and framed back gives nearly the same picture (only the keystone differs), one
    turned by half a pixel does not (its samples fall between). The blurred stages find the camera to a pixel or two
    of the base frame; :func:`phase_fit` then puts the render's samples where the copy's were. Returns the camera and
    the filter."""
    ph, pw = int(picture.shape[0]), int(picture.shape[1])
    part = footprint(camera, base)
    kernel = matched_resampler(render_cameras(model, part)["rgb"][0], picture, framing_of(camera, part))
    h0, w0 = int(base.height[0]), int(base.width[0])
    renderers = {
        False: resampled_renderer(base, kernel),
        True: resampled_renderer(scaled_camera(base, max(1, h0 // 2), max(1, w0 // 2)), kernel),
    }
    target = channel_of(picture.float(), value)
    cam = camera
    for blurs in RESAMPLED_STAGES[-1:] if last else RESAMPLED_STAGES:
        for blur in blurs:
            sigma = blur * max(ph, pw) / 100.0
            renderer = renderers[blur >= RESAMPLED_HALF]
            cam = warp_refine(
                model, cam, target, value, 8, sigma, renders=RESAMPLED_RENDERS, free=FRAMED, renderer=renderer
            )[0]
        cam = phase_fit(model, base, cam, picture, value, kernel)
    return cam, kernel
