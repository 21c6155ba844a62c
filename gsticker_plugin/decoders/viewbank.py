"""The owner's view bank: the base's renders at the camera search's candidate poses, kept beside the owner key.

The camera search (:func:`gsticker_plugin.decoders.pose.estimate_camera`) scores a picture against the base rendered
at every candidate pose at a few pixels' size. Those renders depend on the base (its checkpoint and ``config.yml``),
the model class that renders it, the candidates (count and seed) and the search frame (``side`` rows, ``width``
columns), never on the picture, so they are rendered once and kept in ``KEY.gskey.viewbank/<name>.pt``, where
``name`` is the sha256 of all of these: a changed base names another file and is rendered again.

A bank file holds one tensor, ``[N side width 3]`` RGB in [0, 1], and is read with ``torch.load(weights_only=True)``.
A folder that cannot be written leaves the search to render every time.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import tempfile
from pathlib import Path
from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

from gsticker_plugin.key import file_sha256

BANK_FORMAT = 1
"""Bumped when what a bank file holds, or how its renders are made, changes."""


def bank_folder(key_path: Path) -> Path:
    """Where the view bank of the owner key at ``key_path`` lives: ``KEY.gskey.viewbank`` beside it."""
    return key_path.with_name(key_path.name + ".viewbank")


def bank_name(checkpoint: Path, config: Path, model: str, candidates: int, seed: int, side: int, width: int) -> str:
    """The sha256 (hex) naming the bank file of these renders."""
    what = {
        "format": BANK_FORMAT,
        "checkpoint": file_sha256(checkpoint),
        "config": file_sha256(config),
        "model": model,
        "candidates": candidates,
        "seed": seed,
        "frame": [side, width],
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()


def load_bank(path: Path, count: int, side: int, width: int) -> Optional[Float[Tensor, "N S W 3"]]:
    """The renders in the bank file ``path`` (None when it is missing, unreadable or of another shape)."""
    try:
        rgb = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError, ValueError, pickle.UnpicklingError):
        return None
    if not isinstance(rgb, Tensor) or tuple(rgb.shape) != (count, side, width, 3):
        return None
    return rgb.float()


def save_bank(path: Path, rgb: Float[Tensor, "N S W 3"]) -> bool:
    """Write ``rgb`` to ``path`` (through a temporary file renamed into place: a reader never sees half a file);
    False when the folder cannot be written."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    except OSError:
        return False
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(rgb.detach().float().cpu().contiguous(), f)
        os.replace(tmp, path)
    except OSError:
        Path(tmp).unlink(missing_ok=True)
        return False
    return True
