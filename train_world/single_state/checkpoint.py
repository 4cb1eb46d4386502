"""Training checkpoints without pickle: one safetensors file (tensors) whose header metadata holds a JSON
document (step, config, numpy RNG state, ...). Written atomically (temp file + ``os.replace``), so a killed
run always leaves the previous complete checkpoint.

Adam moments and step counts are stored as tensors and the torch generator state as a uint8 tensor, so
a resumed run continues bit for bit. The JSON document carries a SHA-256 of every tensor's name, dtype, shape
and bytes, so a checkpoint with flipped bytes is refused rather than resumed from.
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from dsg_gym.io.atomic import atomic_write_bytes

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "CheckpointError",
    "load_checkpoint",
    "optimizer_from_tensors",
    "optimizer_to_tensors",
    "save_checkpoint",
    "tensor_digest",
]

CHECKPOINT_FORMAT = "dsg-train-checkpoint"
CHECKPOINT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (truncated, foreign, other version)."""


def tensor_digest(tensors: dict[str, torch.Tensor]) -> str:
    """SHA-256 over the tensors in name order (name, dtype, shape and raw bytes of each)."""
    h = hashlib.sha256()
    for k in sorted(tensors):
        t = tensors[k].detach().contiguous()
        h.update(f"{k}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy())
    return h.hexdigest()


def save_checkpoint(path: str | Path, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    tensors = {k: v.detach().contiguous() for k, v in tensors.items()}
    doc = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        **meta,
        "sha256": tensor_digest(tensors),
    }
    atomic_write_bytes(path, st_save(tensors, metadata={"json": json.dumps(doc)}))


def load_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise CheckpointError(f"{p}: cannot read checkpoint ({e})") from e
    if len(data) < 8:
        raise CheckpointError(f"{p}: truncated checkpoint ({len(data)} bytes)")
    (hlen,) = struct.unpack("<Q", data[:8])
    if 8 + hlen > len(data):
        raise CheckpointError(f"{p}: truncated checkpoint (header says {hlen} bytes, file has {len(data)})")
    try:
        header = json.loads(data[8 : 8 + hlen])
        doc = json.loads(header["__metadata__"]["json"])
    except (ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{p}: not a dsg-train checkpoint ({e})") from e
    if doc.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{p}: not a dsg-train checkpoint (format {doc.get('format')!r})")
    if doc.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{p}: checkpoint version {doc.get('version')!r} is not supported (expected {CHECKPOINT_VERSION})"
        )
    try:
        tensors = st_load(data)
    except Exception as e:  # safetensors raises its own error types for corrupt data
        raise CheckpointError(f"{p}: corrupt or truncated checkpoint ({e})") from e
    if "sha256" in doc and tensor_digest(tensors) != doc["sha256"]:
        raise CheckpointError(f"{p}: corrupt checkpoint (tensor data does not match its SHA-256)")
    return tensors, doc


def optimizer_to_tensors(prefix: str, opt: torch.optim.Optimizer) -> dict[str, torch.Tensor]:
    """Adam state of a single-parameter optimiser as tensors ``{prefix/step, prefix/exp_avg, ...}``."""
    out: dict[str, torch.Tensor] = {}
    for gi, group in enumerate(opt.param_groups):
        for pi, p in enumerate(group["params"]):
            st = opt.state.get(p)
            if not st:
                continue
            for key in ("step", "exp_avg", "exp_avg_sq"):
                if key in st:
                    v = st[key]
                    out[f"{prefix}/{gi}.{pi}/{key}"] = v if isinstance(v, torch.Tensor) else torch.tensor(v)
    return out


def optimizer_from_tensors(prefix: str, opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor]) -> None:
    for gi, group in enumerate(opt.param_groups):
        for pi, p in enumerate(group["params"]):
            key = f"{prefix}/{gi}.{pi}/"
            if key + "exp_avg" not in tensors:
                continue
            st = {
                k: tensors[key + k].clone() for k in ("step", "exp_avg", "exp_avg_sq") if key + k in tensors
            }
            if st["exp_avg"].shape != p.shape:
                raise CheckpointError(
                    f"checkpoint {prefix}: Adam state shape {tuple(st['exp_avg'].shape)} != parameter "
                    f"{tuple(p.shape)}"
                )
            opt.state[p] = st
