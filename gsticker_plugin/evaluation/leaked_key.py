"""The leaked-key attack: someone holding the owner key and the base removes the mark from an image within a PSNR
budget by gradient steps against the informed image decoder."""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin.decoders.fit import (
    fit_message,
    jacobian,
)
from gsticker_plugin.decoders.image import (
    ImageReferenceView,
    image_at_rays,
    image_change_jacobian,
    predict_image_change,
)
from gsticker_plugin.errors import GStickerError
from gsticker_plugin.sticker import Sticker


def leaked_key_attack(
    ref: ImageReferenceView,
    sticker: Sticker,
    image: Float[Tensor, "H W 3"],
    psnr_budget: float,
    steps: int = 100,
    margin: float = 0.25,
) -> Float[Tensor, "H W 3"]:
    """White-box removal by someone who holds the owner key (sticker, gates) and the base (the shared model with
    the sticker off): projected gradient descent on this decoder, at a PSNR budget.

    The attacker fits the message as the decoder does (``s0``), linearizes the decoder there (``J``: the image
    change per unit of ``s``) and looks for the perturbation ``delta`` with ``|delta|^2 <= 3 H W 10^(-budget/10)``
    (PSNR of the attacked image against the given one >= ``psnr_budget`` before rounding and clamping) that drives
    every fitted bit across zero: ``min sum_i relu(margin + sign(s0_i) s_i(delta))``. Only ``delta`` in ``J``'s
    column space moves the least-squares fit, so with ``J = Q R`` it is ``delta = Q u``, ``s(delta) = s0 + R^-1 u``
    and the L2 ball is ``|u| <= eps``: PGD on ``u`` with an exact projection. Pixels outside the decoder's rays are
    left alone. Deterministic; the result is clamped to [0, 1] (quantize it as a saved file would be).
    """

    if psnr_budget <= 0:
        raise GStickerError(f"leaked_key: a PSNR budget in dB > 0, got {psnr_budget}")
    v = ref.view
    rays = v.rays
    out = image.float().clone()
    if rays.numel() == 0:
        return out
    target = (image_at_rays(out, rays, v.hw) - ref.base_rgb).reshape(-1)
    predict = lambda x: predict_image_change(ref, sticker, x)  # noqa: E731
    fit = fit_message(predict, target, sticker.num_bits, jac=lambda x: image_change_jacobian(ref, sticker, x))
    s0 = fit.signs.double()
    jac = image_change_jacobian(ref, sticker, fit.signs)
    if jac is None:
        jac = jacobian(lambda x: predict(x).reshape(-1), fit.signs)
    q, r = torch.linalg.qr(jac.double())
    keep = torch.diagonal(r).abs() > 1e-9 * float(torch.diagonal(r).abs().max().clamp_min(1e-30))
    q, r = q[:, keep], r[keep][:, keep]  # bits the image does not determine: the attacker has nothing to move
    h, w = v.hw
    eps = (3.0 * h * w * 10.0 ** (-psnr_budget / 10.0)) ** 0.5
    sign = torch.sign(s0[keep])
    rinv = torch.linalg.inv(r)
    u = torch.zeros(q.shape[1], dtype=torch.float64)
    lr = eps / 10.0
    for _ in range(steps):
        u.requires_grad_(True)
        loss = torch.relu(margin + sign * (s0[keep] + rinv @ u)).sum()
        (grad,) = torch.autograd.grad(loss, u)
        with torch.no_grad():
            gn = grad.norm()
            if gn == 0:  # every bit already across zero with the margin
                break
            u = u - lr * grad / gn
            n = u.norm()
            u = u * (eps / n) if n > eps else u
    delta = (q @ u.detach()).reshape(-1, 3).float()
    flat = out.reshape(-1, 3)
    flat[rays] = flat[rays] + delta
    return out.clamp(0.0, 1.0)
