"""Pseudo ground truth (paper 3.4): each training view rendered from the *initial* maps at the
LR render resolution, tonemapped to sRGB and upscaled by the image prior.

Targets depend only on their inputs, so each is computed once and cached, keyed by a SHA-256
of everything it depends on (init maps, mesh, materials, light, prior name, scale, camera,
resolution, background):

* in memory, per process, bounded in bytes (a benchmark or a worker re-running a job reuses
  them), and
* on disk under ``cache_dir`` when given (``<key>.pt``, written atomically), so a retried job
  does not recompute them.

Targets are stored as uint16 (N = round(65535 x)): a run that computes a target and a run that
reads it back from the cache see exactly the same numbers (error < 8e-6, far below what the
8-bit output can show) at half the memory of float32.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections import OrderedDict
from dataclasses import fields, is_dataclass
from pathlib import Path

import numpy as np
import torch

from .. import runtime

_Q = 65535.0


def quantize(img: torch.Tensor) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> its uint16 counterpart (numpy, on the host)."""
    q = torch.round(torch.nan_to_num(img.detach().float(), nan=0.0).clamp(0, 1) * _Q)
    return q.to(torch.int32).cpu().numpy().astype(np.uint16)


def dequantize(q: np.ndarray, device: torch.device) -> torch.Tensor:
    """uint16 (H, W, 3) -> float32 tensor in [0, 1] on ``device``."""
    return torch.from_numpy(q.astype(np.float32) / _Q).to(device)


class _MemoryCache:
    """LRU of uint16 targets; ``max_bytes`` None: the runtime's ``pseudo_gt_cache_mb``."""

    def __init__(self, max_bytes: int | None = None):
        self._max_bytes = max_bytes
        self.items: OrderedDict[str, np.ndarray] = OrderedDict()
        self.bytes = 0

    @property
    def max_bytes(self) -> int:
        if self._max_bytes is not None:
            return self._max_bytes
        return runtime.current().pseudo_gt_cache_mb * 2**20

    def get(self, key: str) -> np.ndarray | None:
        v = self.items.get(key)
        if v is not None:
            self.items.move_to_end(key)
        return v

    def put(self, key: str, value: np.ndarray) -> None:
        if value.nbytes > self.max_bytes:
            return
        if key in self.items:
            self.bytes -= self.items.pop(key).nbytes
        self.items[key] = value
        self.bytes += value.nbytes
        while self.bytes > self.max_bytes and self.items:
            _, old = self.items.popitem(last=False)
            self.bytes -= old.nbytes

    def clear(self) -> None:
        self.items.clear()
        self.bytes = 0


MEMORY_CACHE = _MemoryCache()


def _feed(h, obj, depth: int = 0) -> None:
    """Hash an object tree of tensors, arrays, numbers, strings, dataclasses, dicts, lists."""
    if depth > 6:
        return
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(str((t.dtype, tuple(t.shape))).encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        h.update(str((a.dtype, a.shape)).encode())
        h.update(a.tobytes())
    elif isinstance(obj, dict):
        for k in sorted(obj, key=str):
            h.update(str(k).encode())
            _feed(h, obj[k], depth + 1)
    elif isinstance(obj, (list, tuple, set, frozenset)):
        items = sorted(obj, key=str) if isinstance(obj, (set, frozenset)) else obj
        h.update(f"[{len(items)}".encode())
        for v in items:
            _feed(h, v, depth + 1)
    elif is_dataclass(obj) and not isinstance(obj, type):
        h.update(type(obj).__name__.encode())
        for f in fields(obj):
            h.update(f.name.encode())
            _feed(h, getattr(obj, f.name), depth + 1)
    elif isinstance(obj, (int, float, str, bool, bytes)) or obj is None:
        h.update(repr(obj).encode())
    elif hasattr(obj, "__dict__"):
        h.update(type(obj).__name__.encode())
        _feed(h, {k: v for k, v in vars(obj).items() if not k.startswith("_")}, depth + 1)
    else:
        h.update(repr(obj).encode())


def content_hash(*objs) -> str:
    """SHA-256 hex digest of an object tree (see :func:`_feed` for what is looked at)."""
    h = hashlib.sha256()
    for o in objs:
        _feed(h, o)
    return h.hexdigest()


def _disk_path(cache_dir: Path, key: str) -> Path:
    return cache_dir / f"{key}.npy"


def load_cached(key: str, cache_dir: Path | None) -> np.ndarray | None:
    """The cached uint16 target for ``key`` (memory first, then disk), or None."""
    v = MEMORY_CACHE.get(key)
    if v is not None:
        return v
    if cache_dir is None:
        return None
    p = _disk_path(cache_dir, key)
    if not p.is_file():
        return None
    try:
        v = np.load(p, allow_pickle=False)
    except (OSError, ValueError):
        return None  # corrupt or partial file: recompute
    if v.dtype != np.uint16 or v.ndim != 3:
        return None
    MEMORY_CACHE.put(key, v)
    return v


def store_cached(key: str, value: np.ndarray, cache_dir: Path | None) -> None:
    """Keep ``value`` in memory and, when ``cache_dir`` is set, on disk (atomic rename; disk
    errors only cost a recomputation later, so they are ignored)."""
    MEMORY_CACHE.put(key, value)
    if cache_dir is None:
        return
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=cache_dir, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.save(f, value, allow_pickle=False)
        os.replace(tmp, _disk_path(cache_dir, key))
    except OSError:
        pass


def mapped(key: str, cache_dir: Path | None, fallback: np.ndarray) -> np.ndarray:
    """A read-only memory map of the disk copy of ``key`` when there is one, else
    ``fallback`` (so many large targets need not all sit in memory)."""
    if cache_dir is None:
        return fallback
    try:
        m = np.load(_disk_path(cache_dir, key), mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError):
        return fallback
    return m if m.shape == fallback.shape and m.dtype == fallback.dtype else fallback
