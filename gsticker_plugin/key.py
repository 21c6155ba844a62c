"""The owner key: the secret half of a GeometrySticker watermark, stored apart from the shareable model.

It holds the message bits, the extractor and classifier weights, a reference to the base run, (version 2) the
*geometry reference* -- the sticker's configuration and weights, the gates' state, the wrapped fields and their
position normalization -- for the informed geometric decoder (gsticker_plugin.geometry), and a sha256 fingerprint
over all of it (tamper check). Written atomically (temporary file + rename). Version-1 keys (no geometry
reference) still load; ``ns-verify-owner export-key`` adds the reference from the watermarked run.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import torch
from torch import Tensor

from gsticker_plugin.errors import GStickerError

KEY_FORMAT = "gsticker-owner-key"
KEY_VERSION = 2
READABLE_VERSIONS = (1, 2)
KEY_SUFFIX = ".gskey"


def message_from_owner_id(owner_id: str, num_bits: int = 48) -> Tensor:
    """Deterministic message bits from an owner ID string (first ``num_bits`` bits of its sha256)."""
    if not owner_id:
        raise GStickerError("empty owner ID; pass --pipeline.owner-id NAME or --pipeline.message with 0/1 bits")
    digest = hashlib.sha256(("gsticker-owner:" + owner_id).encode("utf-8")).digest()
    bits = [(digest[i // 8] >> (7 - i % 8)) & 1 for i in range(num_bits)]
    return torch.tensor(bits, dtype=torch.long)


def parse_message(text: str, num_bits: int = 48) -> Tensor:
    """A message given as a string of 0/1 characters (spaces and underscores ignored)."""
    s = text.replace(" ", "").replace("_", "")
    if len(s) != num_bits or set(s) - {"0", "1"}:
        raise GStickerError(
            f"message must be exactly {num_bits} bits of 0/1, got {len(s)} characters ({text[:60]!r}); "
            f"pass --pipeline.message with {num_bits} zeros and ones, or use --pipeline.owner-id"
        )
    return torch.tensor([int(c) for c in s], dtype=torch.long)


def bits_to_str(bits: Tensor) -> str:
    return "".join(str(int(b)) for b in bits.reshape(-1).tolist())


def _canonical_hash(obj: Any, h: "hashlib._Hash") -> None:
    if isinstance(obj, dict):
        h.update(b"{")
        for k in sorted(obj.keys(), key=str):
            h.update(str(k).encode() + b":")
            _canonical_hash(obj[k], h)
        h.update(b"}")
    elif isinstance(obj, (list, tuple)):
        h.update(b"[")
        for v in obj:
            _canonical_hash(v, h)
        h.update(b"]")
    elif isinstance(obj, Tensor):
        t = obj.detach().cpu().contiguous().reshape(-1)
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    else:
        h.update(json.dumps(obj, sort_keys=True, default=str).encode())


def plain(obj: Any) -> Any:
    """Containers of tensors and Python scalars only (numpy scalars and arrays converted): what
    ``torch.load(weights_only=True)`` reads back without any allow-list."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(plain(v) for v in obj)
    if isinstance(obj, Tensor):
        return obj.detach().cpu()
    if type(obj).__module__ == "numpy":
        import numpy as np

        return torch.from_numpy(np.ascontiguousarray(obj)) if isinstance(obj, np.ndarray) else obj.item()
    return obj


def fingerprint(payload: Dict[str, Any]) -> str:
    h = hashlib.sha256()
    _canonical_hash({k: v for k, v in payload.items() if k != "fingerprint"}, h)
    return h.hexdigest()


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


@dataclass
class OwnerKey:
    """Everything the owner needs to verify a suspect model or images; keep it secret."""

    owner_id: str
    message: Tensor
    heads_config: Dict[str, Any]
    heads_state: Dict[str, Tensor]
    base: Dict[str, Any] = field(default_factory=dict)
    model_run: str = ""
    null: Optional[Dict[str, Any]] = None
    training_state: Dict[str, Any] = field(default_factory=dict)
    created: float = field(default_factory=time.time)
    geometry: Optional[Dict[str, Any]] = None
    """The geometry reference (sticker config and state, gates' state, fields, aabbs; see
    :func:`gsticker_plugin.geometry.geometry_reference`); None in a version-1 key."""
    version: int = KEY_VERSION
    """The version the key was read as (saving always writes the current version)."""

    @property
    def num_bits(self) -> int:
        return int(self.message.numel())

    def payload(self) -> Dict[str, Any]:
        p = {
            "format": KEY_FORMAT,
            "version": KEY_VERSION,
            "owner_id": self.owner_id,
            "message": self.message.to(torch.long).cpu(),
            "heads_config": dict(self.heads_config),
            "heads_state": {k: v.detach().cpu() for k, v in self.heads_state.items()},
            "base": plain(dict(self.base)),
            "model_run": self.model_run,
            "null": plain(self.null),
            "training_state": plain(self.training_state),
            "created": self.created,
            "geometry": plain(self.geometry),
        }
        p["fingerprint"] = fingerprint(p)
        return p

    def save(self, path: Path) -> Path:
        """Atomic write: a crash leaves the previous key (or none), never half a key."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        torch.save(self.payload(), buf)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(buf.getvalue())
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return path

    @classmethod
    def load(cls, path: Path) -> "OwnerKey":
        path = Path(path)
        if not path.is_file():
            raise GStickerError(f"owner key {path} does not exist; pass --key with the .gskey file ns-train wrote")
        try:
            p = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # not a torch file, truncated, or holding arbitrary objects
            raise GStickerError(f"{path} is not a readable gsticker owner key ({type(e).__name__}); "
                                "pass the .gskey file written by `ns-train geometrysticker`") from None
        if not isinstance(p, dict) or p.get("format") != KEY_FORMAT:
            raise GStickerError(f"{path} is not a gsticker owner key (wrong format); pass the .gskey file "
                                "written by `ns-train geometrysticker`")
        if p.get("version") not in READABLE_VERSIONS:
            raise GStickerError(f"{path} is an owner key of version {p.get('version')}, this gsticker reads "
                                f"versions {', '.join(map(str, READABLE_VERSIONS))}; use the gsticker release that wrote it")
        if p.get("fingerprint") != fingerprint(p):
            raise GStickerError(f"{path} failed its fingerprint check (tampered or corrupted); use your "
                                "original copy of the owner key")
        return cls(owner_id=p["owner_id"], message=p["message"], heads_config=p["heads_config"],
                   heads_state=p["heads_state"], base=p["base"], model_run=p["model_run"], null=p["null"],
                   training_state=p.get("training_state") or {}, created=p["created"],
                   geometry=p.get("geometry") if p["version"] >= 2 else None, version=int(p["version"]))

    def build_heads(self):
        from gsticker_plugin.heads import HeadConfig, Heads

        heads = Heads(HeadConfig(**self.heads_config), self.num_bits)
        heads.load_state_dict(self.heads_state, strict=True)
        return heads.eval()
