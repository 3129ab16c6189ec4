"""``load_prior(name, device)``: priors by name, loaded once per process and reused.

Names: ``bicubic``, the shipped texture sets (``pbr-srmd``, ``pbr-upconv7``: trained on PBR
textures, :data:`pbrsr_core.prior.texture.SHIPPED`), ``waifu2x-photo``, ``rrdn-thick``,
``texture:<weights folder or file>`` (``pbrsr priors train``), ``spandrel:<weights path>``,
``diffusion:<local model dir>``. An unknown name raises
:class:`pbrsr_core.errors.InvalidOptions`; a prior that is not installed raises
:class:`pbrsr_core.errors.PriorUnavailable` naming what to run.
"""

from __future__ import annotations

import threading
from pathlib import Path

import torch

from ..errors import InvalidOptions
from ..options import DEFAULT_PRIOR
from .base import Prior
from .texture import SHIPPED

BUILTIN = ("bicubic", "rrdn-thick", "waifu2x-photo", *SHIPPED)
PREFIXES = ("spandrel:", "diffusion:", "texture:")

_cache: dict[tuple[str, str], Prior] = {}
_lock = threading.RLock()  # reentrant: a texture prior loads its fallback while built


def _key(name: str) -> str:
    """Cache key: built-in names as they are, path-based names with the resolved path."""
    for prefix in PREFIXES:
        if name.startswith(prefix):
            return prefix + str(Path(name[len(prefix) :]).expanduser().resolve())
    return name


def check_name(name: str) -> None:
    """Raise :class:`InvalidOptions` unless ``name`` is a prior name pbrsr knows."""
    if name in BUILTIN:
        return
    for prefix in PREFIXES:
        if name.startswith(prefix):
            if not name[len(prefix) :].strip():
                raise InvalidOptions(f"prior {name!r} needs a path after '{prefix}'")
            return
    raise InvalidOptions(
        f"unknown prior {name!r}: use {', '.join(SHIPPED)}, waifu2x-photo, rrdn-thick, bicubic, "
        "texture:<weights folder or file>, spandrel:<weights file> or "
        "diffusion:<model directory>"
    )


def _build(name: str, device: torch.device) -> Prior:
    if name == "bicubic":
        from .bicubic import BicubicPrior

        return BicubicPrior(device)
    if name == "rrdn-thick":
        from .rrdn import RRDNPrior

        return RRDNPrior(device)
    if name == "waifu2x-photo":
        from .waifu2x import Waifu2xPrior

        return Waifu2xPrior(device)
    if name in SHIPPED:
        from .texture import X2_CANDIDATE, X4_ONLY, TexturePrior, shipped_files

        return TexturePrior(
            shipped_files(name),
            device,
            name=name,
            x4_only=X4_ONLY.get(name, frozenset()),
            x2_candidate=X2_CANDIDATE.get(name, frozenset()),
        )
    if name.startswith("texture:"):
        from .texture import TexturePrior

        return TexturePrior(Path(name[len("texture:") :]).expanduser(), device)
    if name.startswith("spandrel:"):
        from .spandrel_prior import SpandrelPrior

        return SpandrelPrior(Path(name[len("spandrel:") :]).expanduser(), device)
    from .diffusion import DiffusionPrior

    return DiffusionPrior(Path(name[len("diffusion:") :]).expanduser(), device)


def load_prior(name: str = DEFAULT_PRIOR, device: torch.device | str = "cpu") -> Prior:
    """The prior called ``name`` on ``device``, built on first use and cached for the life of
    the process (thread-safe)."""
    check_name(name)
    dev = torch.device(device)
    key = (_key(name), str(dev))
    with _lock:
        prior = _cache.get(key)
        if prior is None:
            prior = _build(name, dev)
            _cache[key] = prior
        return prior


def clear_cache() -> None:
    """Forget every loaded prior (tests; freeing GPU memory)."""
    with _lock:
        _cache.clear()


def list_priors() -> list[dict]:
    """What can be used here, without loading any network: one dict per prior kind with
    ``name``, ``installed`` (bool), ``scales``, ``parameters`` (int or None), ``size_bytes``,
    ``devices`` and ``note`` (what to run or pass)."""
    import importlib.util

    from . import rrdn, waifu2x

    def note(name: str, installed: bool, hint: str) -> str:
        if not installed:
            return hint
        return "default" if name == DEFAULT_PRIOR else ""

    rows = [
        {
            "name": "bicubic",
            "installed": True,
            "scales": [2, 3, 4, 8],
            "parameters": 0,
            "size_bytes": 0,
            "devices": "cpu, cuda",
            "note": "classical reference",
        }
    ]
    params, size = rrdn.installed_stats()
    rows.append(
        {
            "name": "rrdn-thick",
            "installed": rrdn.is_installed(),
            "scales": list(rrdn.SCALES),
            "parameters": params,
            "size_bytes": size,
            "devices": "cpu, cuda",
            "note": note(rrdn.NAME, rrdn.is_installed(), rrdn.INSTALL_HINT),
        }
    )
    files = waifu2x.model_files()
    rows.append(
        {
            "name": waifu2x.NAME,
            "installed": files is not None,
            "scales": list(waifu2x.SCALES),
            "parameters": waifu2x.PARAMETERS if files else None,
            "size_bytes": files[1].stat().st_size if files else None,
            "devices": "cpu, cuda",
            "note": note(waifu2x.NAME, files is not None, waifu2x.INSTALL_HINT),
        }
    )
    from . import texture

    for name in texture.SHIPPED:
        params, size = texture.installed_stats(name)
        rows.append(
            {
                "name": name,
                "installed": params is not None,
                "scales": [2, 4, 8],
                "parameters": params,
                "size_bytes": size,
                "devices": "cpu, cuda",
                "note": note(name, params is not None, "its weights ship with pbrsr"),
            }
        )
    rows.append(
        {
            "name": "texture:<weights>",
            "installed": True,
            "scales": [2, 4, 8],
            "parameters": None,
            "size_bytes": None,
            "devices": "cpu, cuda",
            "note": "weights written by pbrsr priors train/finetune",
        }
    )
    rows.append(
        {
            "name": "spandrel:<weights>",
            "installed": importlib.util.find_spec("spandrel") is not None,
            "scales": "the model's",
            "parameters": None,
            "size_bytes": None,
            "devices": "cpu, cuda",
            "note": "any SR weights spandrel recognises (.pth/.safetensors/.ckpt)",
        }
    )
    has_diffusers = importlib.util.find_spec("diffusers") is not None
    rows.append(
        {
            "name": "diffusion:<model dir>",
            "installed": has_diffusers,
            "scales": [4],
            "parameters": None,
            "size_bytes": None,
            "devices": "cuda (cpu works, very slowly)",
            "note": "local StableDiffusionUpscalePipeline directory"
            if has_diffusers
            else "pip install diffusers transformers",
        }
    )
    return rows
