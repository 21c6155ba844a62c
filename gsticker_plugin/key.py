"""The owner key: the secret half of a GeometrySticker watermark, stored apart from the shareable model.

Holds the message, the extractor and classifier, the base run's reference, the geometry reference (sticker and
gates) for the informed decoders, how the message was drawn, a secret, a commitment salt and an HMAC over the rest
(an integrity check, version 3), (version 4) the owner's Ed25519 public key with a signature over the key's
commitment (authorship: only the holder of the owner identity can sign), and (version 5) the field mark's settings
(levels, secret pattern seed, amplitude) when the shared run carries the mark in its own field. Written atomically. docs/threat-model.md
says what each part proves.

The owner *identity* is an Ed25519 private key in its own file (``$GSTICKER_IDENTITY``, else ``owner.ed25519`` in
the keys folder), created on first use with mode 0600 and reused for every key of that owner; it never enters a key
or a run.
"""

from __future__ import annotations

import hashlib
import hmac
import io
import json
import os
import secrets
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from torch import Tensor

from gsticker_plugin.errors import GStickerError
from gsticker_plugin.heads import HeadConfig, Heads

KEY_FORMAT = "gsticker-owner-key"
KEY_VERSION = 5
READABLE_VERSIONS = (1, 2, 3, 4, 5)
LEGACY_VERSIONS = (1, 2)
"""Versions without integrity (an unkeyed fingerprint anyone can recompute): read only when asked
(``--allow-legacy``)."""
KEY_SUFFIX = ".gskey"
KEYS_DIR_ENV = "GSTICKER_KEYS_DIR"
IDENTITY_ENV = "GSTICKER_IDENTITY"
IDENTITY_NAME = "owner.ed25519"
MESSAGE_SOURCES = ("random", "owner-id", "given")
"""How a key's message was drawn: ``random`` (``secrets``, the only source whose binomial null is exact), derived
from the owner ID (anyone who knows the name knows the bits), or given on the command line."""


def random_message(num_bits: int = 48) -> Tensor:
    """Uniformly random, secret message bits from the operating system's CSPRNG."""
    word = secrets.randbits(num_bits)
    return torch.tensor([(word >> (num_bits - 1 - i)) & 1 for i in range(num_bits)], dtype=torch.long)


def keys_dir() -> Path:
    """The per-user folder where owner keys go by default: ``$GSTICKER_KEYS_DIR``, else
    ``$XDG_DATA_HOME/gsticker/keys`` (``~/.local/share/gsticker/keys``); never inside a run's output folder."""
    env = os.environ.get(KEYS_DIR_ENV)
    if env:
        return Path(env).expanduser()
    data_home = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data_home) / "gsticker" / "keys"


def default_key_path(experiment_name: str, method_name: str, timestamp: str) -> Path:
    """Where ``ns-train geometrysticker`` writes a run's key unless ``--pipeline.key-path`` is given."""
    safe = "-".join(str(x).replace("/", "_").replace(os.sep, "_") for x in (experiment_name, method_name, timestamp))
    return keys_dir() / (safe + KEY_SUFFIX)


def identity_path() -> Path:
    """The owner identity file: ``$GSTICKER_IDENTITY``, else ``owner.ed25519`` in :func:`keys_dir`."""
    env = os.environ.get(IDENTITY_ENV)
    return Path(env).expanduser() if env else keys_dir() / IDENTITY_NAME


def owner_identity(path: Optional[Path] = None) -> Ed25519PrivateKey:
    """The owner's Ed25519 signing key from ``path`` (default :func:`identity_path`), created there (mode 0600,
    atomically) when the file does not exist yet."""
    path = Path(path) if path is not None else identity_path()
    if path.is_file():
        try:
            key = serialization.load_pem_private_key(path.read_bytes(), password=None)
        except (ValueError, TypeError, OSError) as e:
            raise GStickerError(
                f"owner identity {path} is not readable ({type(e).__name__}); restore it from your backup, or point "
                f"${IDENTITY_ENV} at your identity file"
            ) from None
        if not isinstance(key, Ed25519PrivateKey):
            raise GStickerError(f"owner identity {path} is not an Ed25519 private key; point ${IDENTITY_ENV} at yours")
        return key
    if path.exists():
        raise GStickerError(f"owner identity {path} is not a file; point ${IDENTITY_ENV} at a file path")
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(pem)
        os.chmod(tmp, 0o600)
        os.replace(tmp, path)
    except OSError as e:
        raise GStickerError(
            f"cannot write the owner identity {path} ({e.strerror or e}); set ${IDENTITY_ENV} to a writable file path"
        ) from None
    return key


def public_key_hex(identity: Ed25519PrivateKey) -> str:
    """The raw 32-byte public key of an identity, as 64 hex digits (what an owner publishes)."""
    return identity.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw).hex()


def signed_bytes(commitment_hex: str) -> bytes:
    """What a key's signature covers: a domain tag and the commitment."""
    return b"gsticker-key-signature-v1:" + bytes.fromhex(commitment_hex)


def signature_valid(public_hex: str, signature_hex: str, commitment_hex: str) -> bool:
    """Whether ``signature_hex`` is the Ed25519 signature of ``commitment_hex`` under ``public_hex``."""
    try:
        public = Ed25519PublicKey.from_public_bytes(bytes.fromhex(public_hex))
        public.verify(bytes.fromhex(signature_hex), signed_bytes(commitment_hex))
        return True
    except (ValueError, TypeError, InvalidSignature):
        return False


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
    """0/1 bits as a string; an undetermined bit (-1, see gsticker_plugin.decoders.fit.decide_bits) reads ``?``."""
    return "".join("?" if int(b) < 0 else str(int(b)) for b in bits.reshape(-1).tolist())


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
        return torch.from_numpy(np.ascontiguousarray(obj)) if isinstance(obj, np.ndarray) else obj.item()
    return obj


def fingerprint(payload: Dict[str, Any]) -> str:
    """Unkeyed sha256 over a payload (versions 1 and 2): detects corruption, not edits (anyone can recompute it)."""
    h = hashlib.sha256()
    _canonical_hash({k: v for k, v in payload.items() if k not in ("fingerprint", "hmac")}, h)
    return h.hexdigest()


def payload_hmac(payload: Dict[str, Any], secret: bytes) -> str:
    """HMAC-SHA256 of a version-3 payload under the key's own secret (the ``hmac`` entry excluded)."""
    h = hashlib.sha256()
    _canonical_hash({k: v for k, v in payload.items() if k not in ("fingerprint", "hmac")}, h)
    return hmac.new(secret, h.digest(), hashlib.sha256).hexdigest()


COMMITTED_PARTS = ("message", "message_source", "heads_state", "geometry_sticker", "base_sha256", "created")


def commitment(key: "OwnerKey") -> str:
    """sha256 over the salt and the key's secret parts (message, heads, sticker or field mark, base checksum, creation
    time):
    published or timestamped at release, it shows later that this key existed then. Stable across calibration."""
    if not key.salt:
        raise GStickerError(
            "this owner key has no commitment salt (written before version 3); only keys written by "
            "this gsticker can be committed: retrain the sticker to get one"
        )
    parts = {
        "message": key.message.to(torch.long).cpu(),
        "message_source": key.message_source,
        "heads_state": {k: v.detach().cpu() for k, v in key.heads_state.items()},
        "geometry_sticker": plain((key.geometry or {}).get("sticker_state")),
        "base_sha256": (key.base or {}).get("checkpoint_sha256"),
        "created": key.created,
    }
    if key.field_mark is not None:  # the secret pattern seed, amplitude and levels: no other seed can be claimed later
        parts["field_mark"] = plain(key.field_mark)
    h = hashlib.sha256()
    h.update(b"gsticker-commitment-v1:" + bytes.fromhex(key.salt))
    _canonical_hash(parts, h)
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


KEY_FIELDS: Dict[str, Tuple[type, ...]] = {
    "owner_id": (str,),
    "message": (Tensor,),
    "heads_config": (dict,),
    "heads_state": (dict,),
    "base": (dict,),
    "model_run": (str,),
    "null": (dict, type(None)),
    "created": (float, int),
}
"""Fields every readable key holds, with their types (later versions add ``KEY_FIELDS_SINCE``)."""
KEY_FIELDS_SINCE: Dict[int, Dict[str, Tuple[type, ...]]] = {
    2: {"geometry": (dict, type(None))},
    3: {"message_source": (str,), "secret": (str,), "salt": (str,), "training_state": (dict,)},
    4: {"public_key": (str,), "signature": (str,)},
    5: {"field_mark": (dict, type(None))},
}
FIELD_MARK_FIELDS: Dict[str, Tuple[type, ...]] = {
    "table": (str,),
    "levels": (list,),
    "pattern_seed": (int,),
    "amplitude": (float,),
    "init_scale": (float,),
}
"""What a key's field mark holds (:mod:`gsticker_plugin.shared`): the state-dict name of the marked hash table, its
levels, the secret seed of the per-bit patterns, the amplitude and the table's initialization range (the patterns
live on the rows training moved beyond it). A mark in TensoRF's density planes adds ``host`` ("planes") and ``grid`` (the
side of the coarse grid its smooth patterns are drawn on); its ``levels`` are empty."""


def _check_fields(p: Dict[str, Any], version: int, path: Path) -> None:
    """One-line error for a key whose fields are missing or of the wrong type (an integrity check passes on a key
    written by a forger with its own secret)."""
    wanted = dict(KEY_FIELDS)
    for since, more in KEY_FIELDS_SINCE.items():
        if version >= since:
            wanted.update(more)
    for name, types in wanted.items():
        if name not in p:
            raise GStickerError(f"{path} has no {name!r} field; use your original copy of the owner key")
        if not isinstance(p[name], types) or isinstance(p[name], bool):
            raise GStickerError(
                f"{path} holds a malformed {name!r} ({type(p[name]).__name__}); use your original copy of the owner key"
            )
    message = p["message"]
    if message.ndim != 1 or not message.numel() or not bool(((message == 0) | (message == 1)).all()):
        raise GStickerError(
            f"{path} holds a malformed message (not a vector of 0/1 bits); use your original copy of the owner key"
        )
    geometry = p.get("geometry") if version >= 2 else None
    if geometry is not None and not isinstance(geometry.get("sticker_state"), dict):
        raise GStickerError(f"{path} holds a malformed geometry reference; use your original copy of the owner key")
    mark = p.get("field_mark") if version >= 5 else None
    if mark is not None and not all(
        isinstance(mark.get(name), types) and not isinstance(mark.get(name), bool)
        for name, types in FIELD_MARK_FIELDS.items()
    ):
        raise GStickerError(f"{path} holds a malformed field mark; use your original copy of the owner key")


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
    :func:`gsticker_plugin.model.geometry_reference`); None in a version-1 key."""
    message_source: str = "random"
    """How the message was drawn (:data:`MESSAGE_SOURCES`); ``unknown`` for keys written before version 3."""
    owner_message_prob: float = 0.0
    """Share of training renders that carried the owner's message (above 0 the heads and sticker saw it)."""
    secret: str = field(default_factory=lambda: secrets.token_hex(32))
    """HMAC secret of the key file (hex); empty in keys written before version 3."""
    salt: str = field(default_factory=lambda: secrets.token_hex(16))
    """Salt of the key's commitment (hex); empty in keys written before version 3."""
    public_key: str = ""
    """The owner's Ed25519 public key (hex) that signed the commitment; empty in keys written before version 4."""
    signature: str = ""
    """Ed25519 signature of the key's commitment (hex, :func:`signed_bytes`); empty before version 4."""
    field_mark: Optional[Dict[str, Any]] = None
    """The field mark (:data:`FIELD_MARK_FIELDS`) when the shared run carries the message in its own hash table;
    None for a sticker key."""
    version: int = KEY_VERSION
    """The version the key was read as (saving always writes the current version)."""

    @property
    def num_bits(self) -> int:
        return int(self.message.numel())

    def sign(self, identity: Ed25519PrivateKey) -> None:
        """Sign this key's commitment with the owner identity (records the public key beside the signature)."""
        self.public_key = public_key_hex(identity)
        self.signature = identity.sign(signed_bytes(commitment(self))).hex()

    def signed(self) -> bool:
        """Whether the key carries a signature of its own commitment under its own public key."""
        return bool(self.signature) and signature_valid(self.public_key, self.signature, commitment(self))

    def null_caveats(self) -> List[str]:
        """Why the binomial null of this key is not exact (empty: exact): a message that is not uniformly random and
        secret, or training that showed the owner's message to the sticker and heads."""
        out = []
        if self.message_source == "owner-id":
            out.append("the message is derived from the owner ID: anyone who knows the ID knows the bits")
        elif self.message_source == "given":
            out.append("the message was given on the command line: it is uniformly random only if it was drawn so")
        elif self.message_source != "random":
            out.append("the key does not record how its message was drawn (written before version 3)")
        if self.owner_message_prob > 0:
            out.append(
                f"the sticker and heads were trained on the owner's message in {self.owner_message_prob:.0%} "
                "of renders: the decoders may lean toward its bits on unmarked input"
            )
        return out

    def payload(self) -> Dict[str, Any]:
        if not self.secret or not self.salt:
            self.secret = self.secret or secrets.token_hex(32)
            self.salt = self.salt or secrets.token_hex(16)
        p = {
            "format": KEY_FORMAT,
            "version": KEY_VERSION,
            "owner_id": self.owner_id,
            "message": self.message.to(torch.long).cpu(),
            "message_source": self.message_source,
            "owner_message_prob": float(self.owner_message_prob),
            "heads_config": dict(self.heads_config),
            "heads_state": {k: v.detach().cpu() for k, v in self.heads_state.items()},
            "base": plain(dict(self.base)),
            "model_run": self.model_run,
            "null": plain(self.null),
            "training_state": plain(self.training_state),
            "created": self.created,
            "geometry": plain(self.geometry),
            "secret": self.secret,
            "salt": self.salt,
            "public_key": self.public_key,
            "signature": self.signature,
            "field_mark": plain(self.field_mark),
        }
        p["hmac"] = payload_hmac(p, bytes.fromhex(self.secret))
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
    def load(cls, path: Path, allow_legacy: bool = False) -> "OwnerKey":
        """Read a key, checking its integrity (HMAC), its fields and (version 4) its signature; versions 1 and 2 (no
        integrity) only with ``allow_legacy``. Every problem is a one-line :class:`GStickerError`."""
        path = Path(path)
        if not path.is_file():
            raise GStickerError(f"owner key {path} does not exist; pass --key with the .gskey file ns-train wrote")
        try:
            p = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # not a torch file, truncated, or holding arbitrary objects
            raise GStickerError(
                f"{path} is not a readable gsticker owner key ({type(e).__name__}); "
                "pass the .gskey file written by `ns-train geometrysticker`"
            ) from None
        if not isinstance(p, dict) or p.get("format") != KEY_FORMAT:
            raise GStickerError(
                f"{path} is not a gsticker owner key (wrong format); pass the .gskey file "
                "written by `ns-train geometrysticker`"
            )
        if p.get("version") not in READABLE_VERSIONS:
            raise GStickerError(
                f"{path} is an owner key of version {p.get('version')}, this gsticker reads "
                f"versions {', '.join(map(str, READABLE_VERSIONS))}; use the gsticker release that wrote it"
            )
        version = int(p["version"])
        if version in LEGACY_VERSIONS and not allow_legacy:
            raise GStickerError(
                f"{path} is a version-{version} owner key, which has no integrity check (anyone can rewrite it); "
                "pass --allow-legacy to read it anyway, or retrain to get a signed key"
            )
        if version >= 3:
            secret = p.get("secret")
            try:
                ok = isinstance(secret, str) and hmac.compare_digest(
                    str(p.get("hmac")), payload_hmac(p, bytes.fromhex(secret))
                )
            except ValueError:
                ok = False
            if not ok:
                raise GStickerError(
                    f"{path} failed its integrity check (HMAC: edited or corrupted); use your "
                    "original copy of the owner key"
                )
        elif p.get("fingerprint") != fingerprint(p):
            raise GStickerError(
                f"{path} failed its fingerprint check (tampered or corrupted); use your original copy of the owner key"
            )
        _check_fields(p, version, path)
        key = cls(
            owner_id=p["owner_id"],
            message=p["message"],
            heads_config=p["heads_config"],
            heads_state=p["heads_state"],
            base=p["base"],
            model_run=p["model_run"],
            null=p["null"],
            training_state=p.get("training_state") or {},
            created=float(p["created"]),
            geometry=p.get("geometry") if version >= 2 else None,
            message_source=p.get("message_source", "unknown") if version >= 3 else "unknown",
            owner_message_prob=float(p.get("owner_message_prob", 0.0)),
            secret=p.get("secret", "") if version >= 3 else "",
            salt=p.get("salt", "") if version >= 3 else "",
            public_key=p.get("public_key", "") if version >= 4 else "",
            signature=p.get("signature", "") if version >= 4 else "",
            field_mark=p.get("field_mark") if version >= 5 else None,
            version=version,
        )
        if version >= 4 and (key.signature or key.public_key) and not key.signed():
            raise GStickerError(
                f"{path} carries a signature that does not match its commitment and public key (edited or "
                "corrupted); use your original copy of the owner key"
            )
        return key

    def build_heads(self):
        heads = Heads(HeadConfig(**self.heads_config), self.num_bits)
        heads.load_state_dict(self.heads_state, strict=True)
        return heads.eval()
