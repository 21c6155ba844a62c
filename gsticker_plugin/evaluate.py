"""Evaluation helpers shared by the demo and the benchmarks: render a run's views, decode them with a key."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import torch
from torch import Tensor
from tqdm import tqdm

from gsticker_plugin import metrics
from gsticker_plugin.background import background_of
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.runs import final_rgb


def load_pipeline(config_path: Path, test_mode: str = "test"):
    """Stock Nerfstudio loading (what ns-viewer/ns-render/ns-eval do) of any run."""
    # deferred: loads every method entry point, this plugin's included
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(Path(config_path), test_mode=test_mode)
    pipeline.eval()
    return pipeline


@torch.no_grad()
def render_split(
    pipeline, split: str = "test", limit: Optional[int] = None, sticker: Optional[bool] = None, progress: bool = True
) -> Dict[str, Tensor]:
    """Render the cameras of a split; returns {"rgb": [N H W 3], "gt": [N H W 3]} (gt on the model's background)."""
    dm = pipeline.datamanager
    dataset = dm.eval_dataset if split != "train" else dm.train_dataset
    n = len(dataset) if limit is None else min(limit, len(dataset))
    model = pipeline.model
    ctx = model.sticker_enabled(sticker) if (sticker is not None and hasattr(model, "sticker_enabled")) else None
    bg = background_of(model).image_color()
    rgbs: List[Tensor] = []
    gts: List[Tensor] = []
    iterator = range(n)
    if progress:
        iterator = tqdm(iterator, desc=f"rendering {split}", leave=False)
    if ctx is not None:
        ctx.__enter__()
    try:
        for i in iterator:
            camera = dataset.cameras[i : i + 1].to(model.device)
            out = model.get_outputs_for_camera(camera)
            rgbs.append(final_rgb(out).clamp(0, 1).cpu())
            img = dataset.get_image_float32(i)
            if img.shape[-1] == 4:
                img = img[..., :3] * img[..., 3:] + bg * (1.0 - img[..., 3:])
            gts.append(img[..., :3])
    finally:
        if ctx is not None:
            ctx.__exit__(None, None, None)
    return {"rgb": torch.stack(rgbs), "gt": torch.stack(gts)}


@dataclass
class Decoded:
    matches: Tensor  # [N]
    bit_acc: Tensor  # [N]
    pvalues: Tensor  # [N]
    num_bits: int


@torch.no_grad()
def decode_images(key: OwnerKey, images_nhw3: Tensor, batch: int = 16) -> Decoded:
    heads = key.build_heads()
    logits = torch.cat(
        [
            heads.decode(images_nhw3[i : i + batch].permute(0, 3, 1, 2).float())
            for i in range(0, images_nhw3.shape[0], batch)
        ]
    )
    bits = metrics.decode_bits(logits)
    m = metrics.count_matches(bits, key.message)
    return Decoded(
        matches=m,
        bit_acc=metrics.bit_accuracy(bits, key.message),
        pvalues=metrics.binomial_tail_pvalues(m, key.num_bits),
        num_bits=key.num_bits,
    )


def psnr_nhw3(a: Tensor, b: Tensor) -> Tensor:
    return metrics.psnr(a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2))
