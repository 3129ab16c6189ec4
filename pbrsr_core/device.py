"""Device selection: CPU here, CUDA on a render farm; never hard-coded."""

from __future__ import annotations

import torch

from .errors import InvalidOptions


def resolve_device(name: str | None = "auto") -> torch.device:
    """``auto`` picks ``cuda`` when available, else ``cpu``; ``cpu``, ``cuda``, ``cuda:N`` are
    taken as given and checked."""
    if name in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise InvalidOptions(f"unknown device {name!r}: use cpu, cuda or cuda:N") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise InvalidOptions(f"device {name!r} asked for, but CUDA is not available here")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise InvalidOptions(
                f"device {name!r} asked for, but only {torch.cuda.device_count()} GPU(s) exist"
            )
    elif dev.type != "cpu":
        raise InvalidOptions(f"unsupported device type {dev.type!r}: use cpu or cuda")
    return dev
