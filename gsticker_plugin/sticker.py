"""The sticker (message MLP), the gate (Laplace-CDF cover selector) and the density wrap.

``sigma~ = sigma + psi(sigma) * m(gamma(x), M)`` where

* ``psi`` is the *gate*: a Laplace CDF of the base density around ``mu`` with learnable width ``beta``; it
  selects the *cover media*, the samples near surfaces (high density);
* ``m`` is the *sticker*: a small MLP of the positional encoding of the normalized sample position and the
  message bits, scaled to the base's density scale (the gate's ``mu``) and bounded by ``tanh``.

The wrap replaces ``get_density`` on a base field *instance* (not its class), so every path that computes
density goes through it (``forward``, ``density_fn``, TensoRF's direct ``get_density`` calls), and the base
field's state dict is untouched: the sticker and gates live in the GeometrySticker model, not in the field.
With ``WrapState.final_only`` (the model's ``mark_sampling_passes=False``) it marks only the final field's
rendering pass: the passes that place samples see the base's density.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Tuple, Union

import torch
from jaxtyping import Float
from torch import Tensor, nn

from gsticker_plugin.background import Background

# ---------------------------------------------------------------------------------------------- pure functions


def laplace_cdf_gate(sigma: Float[Tensor, "*bs 1"], mu: Tensor, beta: Tensor) -> Float[Tensor, "*bs 1"]:
    """psi = 1/2 + 1/2 sign(sigma - mu) (1 - exp(-|sigma - mu| / beta)): the Laplace CDF at sigma."""
    d = sigma - mu
    return 0.5 + 0.5 * torch.sign(d) * (1.0 - torch.exp(-d.abs() / beta))


def sparsity_loss(psi: Tensor, eps: float = 1e-4) -> Tensor:
    """mean(log psi + log(1 - psi)): lowest when psi is 0 or 1 (clamped so it stays finite)."""
    p = psi.clamp(eps, 1.0 - eps)
    return (torch.log(p) + torch.log1p(-p)).mean() if p.numel() else psi.sum() * 0.0


def positional_encoding(x: Float[Tensor, "*bs 3"], num_frequencies: int) -> Float[Tensor, "*bs enc"]:
    """gamma(x) = [x, sin(2^k pi x), cos(2^k pi x)]_{k < L} for x in [0, 1]^3 (3 + 6L dims)."""
    freqs = (2.0 ** torch.arange(num_frequencies, device=x.device, dtype=x.dtype)) * math.pi
    xb = x[..., None] * freqs  # [*bs, 3, L]
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1).flatten(-2)
    return torch.cat([x, enc], dim=-1)


def normalize_positions(positions: Float[Tensor, "*bs 3"], aabb: Float[Tensor, "2 3"]) -> Float[Tensor, "*bs 3"]:
    """World positions to the sticker's [0, 1]^3 inside ``aabb`` (clamped outside it)."""
    lo, hi = aabb[0].to(positions), aabb[1].to(positions)
    return ((positions - lo) / (hi - lo)).clamp(0.0, 1.0)


def message_to_signs(message: Tensor) -> Tensor:
    """0/1 bits -> -1/+1 float inputs for the sticker."""
    return message.float() * 2.0 - 1.0


def render_weights(density: Float[Tensor, "R S 1"], deltas: Float[Tensor, "R S 1"]) -> Float[Tensor, "R S 1"]:
    """Per-sample weights (same quadrature as Nerfstudio's RaySamples.get_weights)."""
    dd = deltas * density
    alphas = 1.0 - torch.exp(-dd)
    transmittance = torch.cumsum(dd[:, :-1], dim=-2)
    transmittance = torch.cat([torch.zeros_like(transmittance[:, :1]), transmittance], dim=-2)
    return torch.nan_to_num(alphas * torch.exp(-transmittance))


def composite(
    density: Float[Tensor, "R S 1"],
    rgb: Float[Tensor, "R S 3"],
    deltas: Float[Tensor, "R S 1"],
    background: Union[Float[Tensor, " 3"], Background],
) -> Tuple[Float[Tensor, "R 3"], Float[Tensor, "R S 1"]]:
    """Volume rendering (same quadrature as Nerfstudio's RaySamples.get_weights + RGBRenderer) on a colour or a
    :class:`Background` (``last_sample``: each ray's last sample colour)."""
    weights = render_weights(density, deltas)
    acc = weights.sum(dim=-2)
    color = (weights * rgb).sum(dim=-2) + Background.of(background).fill(rgb) * (1.0 - acc)
    return color, weights


# ---------------------------------------------------------------------------------------------- modules


class Gate(nn.Module):
    """Laplace-CDF cover selector with a learnable width, calibrated to one base field's density scale."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mu", torch.tensor(1.0))
        self.register_buffer("scale", torch.tensor(1.0))
        self.register_buffer("calibrated", torch.tensor(False))
        self.log_beta = nn.Parameter(torch.tensor(0.0))

    max_beta_ratio: float = 0.15
    """beta never exceeds this share of mu: the gate stays a surface selector (and the fast path exact)."""

    @property
    def beta(self) -> Tensor:
        return torch.minimum(torch.exp(self.log_beta), self.mu * self.max_beta_ratio)

    @torch.no_grad()
    def calibrate(
        self, density: Tensor, weights: Tensor, quantile: float = 0.5, beta_ratio: float = 0.1, amplitude: float = 10.0
    ) -> None:
        """Set mu to the weight-weighted ``quantile`` of the base density over visible samples, and the sticker's
        largest density change to ``amplitude * mu``.

        Densities differ by orders of magnitude between bases (nerfacto's trunc_exp vs TensoRF's ReLU sums),
        so mu (the gate centre) and the sticker amplitude are both expressed in this base's own units.
        """
        d = density.reshape(-1).float()
        w = weights.reshape(-1).float()
        keep = w > 1e-3
        if keep.sum() < 16:
            raise ValueError("cannot calibrate the gate: the base renders (almost) nothing from these views")
        d, w = d[keep], w[keep]
        order = torch.argsort(d)
        cw = torch.cumsum(w[order], 0)
        idx = torch.searchsorted(cw, quantile * cw[-1]).clamp(max=len(d) - 1)
        mu = d[order][idx].clamp_min(1e-6)
        self.mu.copy_(mu)
        self.scale.copy_(mu * amplitude)
        self.log_beta.copy_(torch.log(mu * beta_ratio))
        self.calibrated.fill_(True)

    def forward(self, sigma: Tensor) -> Tensor:
        return laplace_cdf_gate(sigma, self.mu, self.beta)


class Sticker(nn.Module):
    """Theta_m: sample position and message bits -> density offset m in [-1, 1].

    ``kind="concat"`` is the paper's layout: an MLP of [gamma(x), M] (two hidden layers).
    ``kind="bilinear"`` (default) keeps the same MLP trunk on gamma(x) but mixes the message in linearly:
    ``m = tanh(<f(gamma(x)), 2M - 1> / sqrt(K))``, i.e. every bit owns a learned 3D pattern on the cover
    media and its sign flips that pattern. The extractor then faces a (nearly) linear decoding problem,
    which it learns in a few hundred steps instead of thousands (docs/experiments/sticker-notes.md).
    """

    def __init__(
        self,
        num_bits: int = 48,
        num_frequencies: int = 5,
        hidden_dim: int = 64,
        num_layers: int = 2,
        init_scale: float = 0.1,
        kind: str = "bilinear",
    ):
        super().__init__()
        if kind not in ("concat", "bilinear"):
            raise ValueError(f"unknown sticker kind {kind!r}; use 'bilinear' or 'concat'")
        self.kind = kind
        self.num_bits = num_bits
        self.num_frequencies = num_frequencies
        enc_dim = 3 + 6 * num_frequencies
        # concat: the message part of the first layer is constant per render, folded into a bias.
        self.pos_in = nn.Linear(enc_dim, hidden_dim)
        self.msg_in = nn.Linear(num_bits, hidden_dim, bias=False) if kind == "concat" else None
        layers = []
        for _ in range(num_layers - 1):
            layers += [nn.ReLU(), nn.Linear(hidden_dim, hidden_dim)]
        layers += [nn.ReLU(), nn.Linear(hidden_dim, 1 if kind == "concat" else num_bits)]
        self.mlp = nn.Sequential(*layers)
        # Start visible enough for the extractor to get a gradient; the content loss then shrinks it.
        nn.init.uniform_(self.mlp[-1].weight, -init_scale, init_scale)
        nn.init.zeros_(self.mlp[-1].bias)

    def features(self, positions01: Float[Tensor, "N 3"]) -> Float[Tensor, "N F"]:
        """The message-independent part: concat: the first layer's position term [N hidden]; bilinear: the
        per-bit 3D patterns [N K]."""
        h = self.pos_in(positional_encoding(positions01, self.num_frequencies))
        return h if self.msg_in is not None else self.mlp(h)

    def mix(self, features: Float[Tensor, "N F"], signs: Float[Tensor, " K"]) -> Float[Tensor, "N 1"]:
        """The sticker from :meth:`features` and message *signs* (+-1 for bits; any value in [-1, 1] is allowed,
        which makes the sticker a differentiable function of a continuous message, see gsticker_plugin.decoders.geometric)."""
        if self.msg_in is not None:
            return torch.tanh(self.mlp(features + self.msg_in(signs)))
        return torch.tanh(features @ signs[:, None] / math.sqrt(self.num_bits))

    def mix_jacobian(self, features: Float[Tensor, "N F"], m: Float[Tensor, "N 1"]) -> Optional[Float[Tensor, "N K"]]:
        """d mix / d signs in closed form for the bilinear sticker, from its value ``m`` at those signs:
        ``(1 - m^2) f / sqrt(K)``; None for ``concat`` (its message passes through the MLP: differentiate :meth:`mix`)."""
        if self.msg_in is not None:
            return None
        return (1.0 - m * m) * features / math.sqrt(self.num_bits)

    def forward(self, positions01: Float[Tensor, "N 3"], message: Float[Tensor, " K"]) -> Float[Tensor, "N 1"]:
        return self.mix(self.features(positions01), message_to_signs(message))

    @torch.no_grad()
    def fold(self, message: Tensor) -> Dict[str, Tensor]:
        """The state of a :class:`FoldedSticker` equal to this sticker with ``message`` fixed: bilinear: ``2M - 1``
        folds into the last layer (one output); concat: the message term folds into the first layer's bias."""
        signs = message_to_signs(message).to(self.pos_in.weight)
        state = {k: v.detach().clone() for k, v in self.state_dict().items() if not k.startswith("msg_in.")}
        if self.msg_in is not None:
            state["pos_in.bias"] = self.pos_in.bias + self.msg_in.weight @ signs
            return state
        last = self.mlp[-1]
        name = f"mlp.{len(self.mlp) - 1}"
        state[name + ".weight"] = (signs @ last.weight)[None] / math.sqrt(self.num_bits)
        state[name + ".bias"] = (last.bias @ signs).reshape(1) / math.sqrt(self.num_bits)
        return state


class FoldedSticker(nn.Module):
    """The sticker of one fixed message, ``m = tanh(MLP(gamma(x)))`` with one output: what a shared run holds. Its
    weights carry the message only mixed with the per-bit patterns, which stay in the owner key."""

    def __init__(self, num_frequencies: int = 5, hidden_dim: int = 64, num_layers: int = 2) -> None:
        super().__init__()
        self.num_frequencies = num_frequencies
        self.pos_in = nn.Linear(3 + 6 * num_frequencies, hidden_dim)
        layers = []
        for _ in range(num_layers - 1):
            layers += [nn.ReLU(), nn.Linear(hidden_dim, hidden_dim)]
        layers += [nn.ReLU(), nn.Linear(hidden_dim, 1)]
        self.mlp = nn.Sequential(*layers)

    def forward(self, positions01: Float[Tensor, "N 3"]) -> Float[Tensor, "N 1"]:
        return torch.tanh(self.mlp(self.pos_in(positional_encoding(positions01, self.num_frequencies))))


@dataclass
class WrapState:
    """Mutable switches shared by all wrapped fields of one model."""

    enabled: bool = True
    message: Optional[Tensor] = None
    folded: Optional[FoldedSticker] = None  # used when no message is set (a shared run)
    record: bool = False
    final_only: bool = False  # mark only the final field's rendering pass (not the passes that place samples)
    in_final: bool = False  # set by the model while the final field renders


class DensityWrap:
    """Installs ``sigma + psi * scale * m`` on a field instance's ``get_density``; removable."""

    def __init__(
        self,
        field: nn.Module,
        name: str,
        sticker: Sticker,
        gate: Gate,
        state: WrapState,
        aabb: Tensor,
        gate_threshold: float = 1e-3,
    ) -> None:
        self.field = field
        self.name = name
        self.sticker = sticker
        self.gate = gate
        self.state = state
        self.aabb = aabb
        self.gate_threshold = gate_threshold
        self.original: Callable = field.get_density
        self.last: Dict[str, Tensor] = {}
        self.is_final = False  # set by the model on the field whose samples make the final image
        object.__setattr__(field, "get_density", self.get_density)

    def remove(self) -> None:
        if self.field.__dict__.get("get_density") == self.get_density:
            del self.field.__dict__["get_density"]

    def normalize(self, positions: Tensor) -> Tensor:
        return normalize_positions(positions, self.aabb)

    def open_samples(self, sigma: Tensor) -> Tuple[Tensor, Tensor]:
        """psi at each sample and where the gate is open (psi above the threshold of a calibrated gate): the one
        rule the wrap, the fast path and the decoders share."""
        psi = self.gate(sigma)
        return psi, (psi.detach() > self.gate_threshold).squeeze(-1) & bool(self.gate.calibrated)

    def delta(self, sigma: Tensor, positions: Tensor, message: Optional[Tensor]) -> Tuple[Tensor, Tensor]:
        """The density added at each sample (only evaluated where the gate is open), and psi; ``message`` None:
        the folded sticker of the shared state."""
        psi, open_ = self.open_samples(sigma)
        out = torch.zeros_like(sigma)
        if open_.any():
            pos = self.normalize(positions[open_])
            m = self.sticker(pos, message) if message is not None else self.state.folded(pos)
            out[open_] = psi[open_] * self.gate.scale * m
        return out, psi

    def get_density(self, ray_samples, *args, **kwargs):
        result = self.original(ray_samples, *args, **kwargs)
        density, rest = (result[0], result[1:]) if isinstance(result, tuple) else (result, None)
        marks = not self.state.final_only or (self.is_final and self.state.in_final)
        has_sticker = self.state.message is not None or self.state.folded is not None
        if marks and self.state.enabled and has_sticker and self.gate.calibrated:
            positions = ray_samples.frustums.get_positions()
            delta, _ = self.delta(density, positions.reshape(*density.shape[:-1], 3), self.state.message)
            if self.state.record:
                self.last = {"delta": delta.detach()}
            density = torch.relu(density + delta)
        return (density, *rest) if rest is not None else density
