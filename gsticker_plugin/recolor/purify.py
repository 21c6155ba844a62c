"""Model purification: the recipient fine-tunes every parameter of a shared model on clean training images."""

from __future__ import annotations

from typing import Dict, List, Optional

from torch import Tensor, nn

from gsticker_plugin.background import background_of
from gsticker_plugin.recolor.finetune import finetune_color
from gsticker_plugin.recolor.runs import composite_on, training_images


def purify_parameters(model: nn.Module) -> Dict[str, nn.Parameter]:
    """Every floating-point parameter of ``model`` an attacker can fit (density, colour, sticker, gate width), not the
    scene box nor an extractor or classifier head."""
    return {
        n: p
        for n, p in model.named_parameters()
        if p.is_floating_point() and n.rsplit(".", 1)[-1] != "aabb" and not n.startswith(("extractor", "classifier"))
    }


def clean_targets(model: nn.Module, dataset) -> List[Tensor]:
    """The dataset's training images composited on ``model``'s background: ``[H W 3]`` each."""
    bg = background_of(model).image_color()
    return [composite_on(t, bg) for t in training_images(dataset)]


def purify(
    model: nn.Module,
    cameras,
    targets: List[Tensor],
    steps: int,
    lr: float = 1e-3,
    rays_per_step: int = 1024,
    seed: int = 0,
    progress: bool = True,
    params: Optional[Dict[str, nn.Parameter]] = None,
) -> List[float]:
    """``steps`` steps of Adam on every :func:`purify_parameters` of ``model``, MSE of rendered rays against
    ``targets`` (the clean training images at ``cameras``); the loss per step."""
    params = purify_parameters(model) if params is None else params
    hist = finetune_color(
        model,
        cameras,
        targets,
        steps,
        lr=lr,
        rays_per_step=rays_per_step,
        seed=seed,
        progress=progress,
        color_params=params,
        desc="purifying (every parameter)",
    )
    return hist["loss"]
