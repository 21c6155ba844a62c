"""The frozen blind extractor: a fixed random CNN on the V channel, whitened over clean renders.

It exists (seed, whitening and sha256 recorded) before the owner's message is drawn, so its bits on any image
are independent of the message and the per-view matches of an unmarked image follow Binomial(K, 1/2) exactly.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Dict, Iterable, Optional

import torch
from jaxtyping import Float
from torch import Tensor, nn

GELU_GAIN = math.sqrt(2.0 / 0.425)
"""Weight gain of the GELU stages (E[GELU(z)^2] is about 0.425 for z ~ N(0, 1)); the per-stage scale normalisation
sets each stage's output scale anyway, so the gain only keeps the pre-activations in GELU's curved range."""


def value_channel(images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B 1 H W"]:
    """V = max(R, G, B) minus 0.5: exactly invariant under kornia's HSV hue shift."""
    return images.amax(dim=1, keepdim=True) - 0.5


def state_sha256(module: nn.Module) -> str:
    """sha256 over a module's state (names and float32 bytes, sorted by name)."""
    h = hashlib.sha256()
    for name, t in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().float().numpy().tobytes())
    return h.hexdigest()


@dataclass
class ExtractorConfig:
    """Shape and seed of the frozen blind extractor."""

    seed: int = 0
    """Seed of the random weights (recorded in the owner key with the weights' sha256)."""
    widths: tuple = (32, 64, 64, 128)
    """Channels of the four stride-2 stages (after a 3x3 stem conv to the first width)."""
    num_bits: int = 48
    pca_eps: float = 1e-3
    """Whitening epsilon relative to the mean PCA eigenvalue (an absolute epsilon whitens a tiny spread to 0)."""


class RandomCNN(nn.Module):
    """V channel -> 3x3 conv -> stride-2 stages (GELU) -> global average pool -> linear to K logits, Kaiming fan-in
    initialised with the GELU gain and a per-stage scale normalisation, so activations keep their scale."""

    def __init__(self, config: ExtractorConfig) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(config.seed)
        chans = [1, config.widths[0], *config.widths]
        self.convs = nn.ModuleList()
        for i, (cin, cout) in enumerate(zip(chans[:-1], chans[1:])):
            conv = nn.Conv2d(cin, cout, 3, stride=1 if i == 0 else 2, padding=1, bias=False)
            std = (GELU_GAIN if i else 1.0) / math.sqrt(cin * 9)
            with torch.no_grad():
                conv.weight.copy_(torch.randn(conv.weight.shape, generator=gen) * std)
            self.convs.append(conv)
        self.head = nn.Linear(chans[-1], config.num_bits, bias=False)
        with torch.no_grad():
            self.head.weight.copy_(torch.randn(self.head.weight.shape, generator=gen) / math.sqrt(chans[-1]))
        self.requires_grad_(False)

    def forward(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B K"]:
        x = value_channel(images) * 4.0  # V spans [-0.5, 0.5]: unit scale in
        for conv in self.convs:
            x = nn.functional.gelu(conv(x))
            x = x / x.pow(2).mean(dim=(1, 2, 3), keepdim=True).add(1e-6).sqrt()  # per-image, per-stage scale
        return self.head(x.mean(dim=(-2, -1)))


class Whitening(nn.Module):
    """z = diag(1 / sqrt(lambda + eps)) U^T (y - mean), fitted on the extractor's outputs over clean images."""

    def __init__(self, num_bits: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(num_bits))
        self.register_buffer("matrix", torch.eye(num_bits))

    @torch.no_grad()
    def fit(self, outputs: Float[Tensor, "N K"], relative_eps: float) -> Dict[str, float]:
        """Mean and PCA of ``outputs``; returns the spread it measured (the eigenvalue range)."""
        y = outputs.double()
        mean = y.mean(0)
        cov = torch.cov((y - mean).T)
        lam, vec = torch.linalg.eigh(cov)
        lam = lam.clamp_min(0.0)
        eps = relative_eps * float(lam.mean())
        self.mean.copy_(mean.float())
        self.matrix.copy_((vec / (lam + eps).sqrt()).T.float())
        return {"eig_min": float(lam.min()), "eig_max": float(lam.max()), "eig_mean": float(lam.mean()), "eps": eps}

    def forward(self, y: Float[Tensor, "B K"]) -> Float[Tensor, "B K"]:
        return (y - self.mean) @ self.matrix.T


class BlindExtractor(nn.Module):
    """A network (default: the random CNN) followed by its whitening: whitened logits, one per bit (positive reads
    1). The whitening's mean also removes the scene's own bias per bit, which would otherwise weigh on every view."""

    def __init__(self, config: ExtractorConfig, network: Optional[nn.Module] = None) -> None:
        super().__init__()
        self.config = config
        self.cnn = network if network is not None else RandomCNN(config)
        self.whitening = Whitening(config.num_bits)

    def forward(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B K"]:
        return self.whitening(self.cnn(images))

    @torch.no_grad()
    def fit_whitening(self, batches: Iterable[Tensor]) -> Dict[str, float]:
        """Whiten over the raw outputs of ``batches`` of clean (possibly distorted) images [B 3 H W]."""
        ys = torch.cat([self.cnn(b) for b in batches])
        stats = self.whitening.fit(ys, self.config.pca_eps)
        stats["raw_std_across_images"] = float(ys.std(0).mean())
        stats["samples"] = ys.shape[0]
        return stats

    def sha256(self) -> str:
        """Hash of every weight and whitening buffer (the key records it before the message is drawn)."""
        return state_sha256(self)


@dataclass
class LearnedExtractorConfig:
    """Shape of the pre-trained blind extractor (trained on synthetic marks of random messages, then frozen)."""

    seed: int = 0
    widths: tuple = (32, 64, 64, 128)
    grid: int = 4
    """Cells per side of the grid pooling (keeps where on the image a bit's pattern is)."""
    num_bits: int = 48


class LearnedExtractor(nn.Module):
    """[V - 0.5, x, y] -> 3x3 stem -> stride-2 stages (GroupNorm, GELU) -> grid pooling -> linear to K logits."""

    def __init__(self, config: LearnedExtractorConfig) -> None:
        super().__init__()
        self.config = config
        w = config.widths
        with torch.random.fork_rng(devices=[]):  # seeded initialisation, the caller's random state untouched
            torch.manual_seed(config.seed)
            layers = [nn.Conv2d(3, w[0], 3, padding=1), nn.GroupNorm(4, w[0]), nn.GELU()]
            cin = w[0]
            for cout in w:
                layers += [nn.Conv2d(cin, cout, 3, stride=2, padding=1), nn.GroupNorm(4, cout), nn.GELU()]
                cin = cout
            self.backbone = nn.Sequential(*layers)
            self.head = nn.Linear(cin * config.grid * config.grid, config.num_bits)

    def forward(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B K"]:
        b, _, h, w = images.shape
        ys = torch.linspace(-1, 1, h, device=images.device, dtype=images.dtype)
        xs = torch.linspace(-1, 1, w, device=images.device, dtype=images.dtype)
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        coords = torch.stack([gx, gy])[None].expand(b, 2, h, w)
        x = torch.cat([value_channel(images) * 4.0, coords], dim=1)
        x = nn.functional.adaptive_avg_pool2d(self.backbone(x), self.config.grid)
        return self.head(x.flatten(1))

    def sha256(self) -> str:
        return state_sha256(self)
