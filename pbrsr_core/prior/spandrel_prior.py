"""``spandrel:<weights file>``: any single-image SR model the ``spandrel`` library recognises
(Real-ESRGAN/ESRGAN, Compact, SwinIR, HAT, DAT, OmniSR, SPAN, ...; .pth, .pt, .ckpt,
.safetensors). spandrel unpickles .pth files with a restricted unpickler.

torchvision: spandrel 0.4.2 imports ``torchvision.transforms.functional`` in two non-SR
architectures only (LaMa inpainting: ``rotate``/``InterpolationMode``; RestoreFormer face
restoration: ``normalize``). Where torchvision imports (a CUDA farm), it is used as is. Where it
does not (here: PyPI's torchvision cannot load beside the CPU torch build), :func:`import_spandrel`
registers a stand-in ``torchvision.transforms.functional`` *only while* ``import spandrel``
runs, then removes it from ``sys.modules`` so nothing else sees it. The stand-in's functions
raise :class:`PriorUnavailable` ("this architecture needs torchvision") if ever called, which
can only happen for those two architectures, and they are refused below anyway (not SR).
"""

from __future__ import annotations

import enum
import sys
import threading
import types
from pathlib import Path

import torch

from ..errors import InvalidOptions, PriorUnavailable
from .base import Prior

_import_lock = threading.Lock()
_spandrel = None


def _needs_torchvision(name: str):
    def missing(*_args, **_kwargs):
        raise PriorUnavailable(
            f"this architecture needs torchvision (torchvision.transforms.functional.{name}), "
            "which does not import here: install a torchvision build matching your torch"
        )

    missing.__name__ = name
    return missing


class _InterpolationMode(enum.Enum):
    NEAREST = "nearest"
    NEAREST_EXACT = "nearest-exact"
    BILINEAR = "bilinear"
    BICUBIC = "bicubic"
    BOX = "box"
    HAMMING = "hamming"
    LANCZOS = "lanczos"


def _standin_modules() -> dict[str, types.ModuleType]:
    """``torchvision``, ``torchvision.transforms``, ``torchvision.transforms.functional``
    stand-ins; any function looked up on the last one raises PriorUnavailable when called."""
    tv = types.ModuleType("torchvision")
    tv.__path__ = []  # a package, so submodules resolve
    tr = types.ModuleType("torchvision.transforms")
    tr.__path__ = []
    fn = types.ModuleType("torchvision.transforms.functional")
    vars(fn).update(
        InterpolationMode=_InterpolationMode,
        __getattr__=lambda name: (
            _needs_torchvision(name) if not name.startswith("__") else _raise_attr(name)
        ),
    )
    vars(tv)["transforms"] = tr
    vars(tr)["functional"] = fn
    return {m.__name__: m for m in (tv, tr, fn)}


def _raise_attr(name: str):
    raise AttributeError(name)


def _drop(prefix: str) -> None:
    for key in [k for k in sys.modules if k == prefix or k.startswith(prefix + ".")]:
        del sys.modules[key]


def import_spandrel():
    """Import and return the ``spandrel`` module, with the torchvision stand-in described in
    the module docstring when the real torchvision does not import."""
    global _spandrel
    with _import_lock:
        if _spandrel is not None:
            return _spandrel
        try:
            import torchvision.transforms.functional  # noqa: F401

            real_tv = True
        except Exception:  # not installed, or a build that does not match torch
            _drop("torchvision")  # a failed import can leave half-initialised modules
            real_tv = False
        if real_tv:
            import spandrel
        else:
            standins = _standin_modules()
            sys.modules.update(standins)
            try:
                import spandrel
            except Exception:
                _drop("spandrel")
                raise
            finally:
                for name, mod in standins.items():
                    if sys.modules.get(name) is mod:
                        del sys.modules[name]
        _spandrel = spandrel
        return spandrel


def _sr_descriptor(load, label: str):
    """The spandrel descriptor ``load()`` returns (``label`` names its source in errors),
    refused unless it is a single-image SR model from RGB to RGB at x2 or more."""
    try:
        spandrel = import_spandrel()
    except ImportError as exc:
        raise PriorUnavailable("spandrel priors need `pip install spandrel`") from exc
    try:
        desc = load(spandrel)
    except spandrel.UnsupportedModelError as exc:
        raise InvalidOptions(f"'{label}' is not a model architecture spandrel recognises") from exc
    except (ValueError, RuntimeError, OSError, KeyError) as exc:
        raise InvalidOptions(f"cannot load the prior weights '{label}': {exc}") from exc
    if not isinstance(desc, spandrel.ImageModelDescriptor) or desc.purpose not in ("SR", "FaceSR"):
        raise InvalidOptions(
            f"'{label}' is a {desc.architecture.name} model for "
            f"{getattr(desc, 'purpose', 'another task')}, not single-image super-resolution"
        )
    if desc.input_channels != 3 or desc.output_channels != 3 or desc.scale < 2:
        raise InvalidOptions(
            f"'{label}' maps {desc.input_channels} to {desc.output_channels} channels "
            f"at x{desc.scale}; a prior must map RGB to RGB at x2 or more"
        )
    return desc


def load_descriptor(path: Path, device: torch.device | str = "cpu"):
    """The SR model in the weights file ``path``, a spandrel descriptor (:func:`_sr_descriptor`)."""
    path = Path(path)
    if not path.is_file():
        raise InvalidOptions(f"the prior weights file '{path.name}' does not exist")
    return _sr_descriptor(lambda s: s.ModelLoader(device).load_from_file(path), path.name)


class SpandrelNet(torch.nn.Module):
    """A spandrel SR model as a network a texture prior trains and runs
    (:mod:`pbrsr_core.prior.train`): ``net(x)`` takes (B, 3, h, w) in [0, 1] of any size
    (padded to the model's size requirements as spandrel pads, the padding cut off the
    output) to (B, 3, s*h, s*w), with gradients. ``architecture`` is spandrel's id of it;
    :meth:`weights` the state dict spandrel recognises it by."""

    widths: tuple[int, ...] = ()

    def __init__(self, desc) -> None:
        super().__init__()
        self.model = desc.model
        self.architecture = str(desc.architecture.id)
        self.stride = int(desc.scale)
        self.requirements = desc.size_requirements

    @classmethod
    def from_file(cls, path: Path) -> SpandrelNet:
        return cls(load_descriptor(path))

    @classmethod
    def from_weights(cls, state: dict[str, torch.Tensor], label: str) -> SpandrelNet:
        return cls(_sr_descriptor(lambda s: s.ModelLoader().load_from_state_dict(state), label))

    def weights(self) -> dict[str, torch.Tensor]:
        return self.model.state_dict()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        pad_w, pad_h = self.requirements.get_padding(w, h)
        if pad_w or pad_h:  # reflect as far as it reaches, then replicate (as spandrel)
            rw, rh = min(pad_w, w - 1), min(pad_h, h - 1)
            x = torch.nn.functional.pad(x, (0, rw, 0, rh), mode="reflect")
            x = torch.nn.functional.pad(x, (0, pad_w - rw, 0, pad_h - rh), mode="replicate")
        return self.model(x)[..., : h * self.stride, : w * self.stride]


class SpandrelPrior(Prior):
    """A spandrel-loaded SR model (3 channels in and out, scale >= 2)."""

    bytes_per_pixel = 16384.0  # transformers (SwinIR, HAT) need far more than CNNs
    default_overlap = 32

    def __init__(self, path: Path, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.device = torch.device(device)
        path = Path(path)
        self.name = f"spandrel:{path.name}"
        desc = load_descriptor(path, self.device)
        self.descriptor = desc.eval().to(self.device)
        self.architecture = desc.architecture.name
        self.scales = (int(desc.scale),)
        req = desc.size_requirements
        self.min_size = max(1, int(req.minimum))
        if desc.tiling == import_spandrel().ModelTiling.INTERNAL:
            self.tile_size = 1 << 20  # never tile: the model needs the whole image
        self._lock = threading.Lock()

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.descriptor.model.parameters())

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        """x (B, 3, h, w) -> (B, 3, s*h, s*w); spandrel pads to the model's size needs."""
        with self._lock:  # one module, possibly shared by worker threads
            return torch.cat([self.descriptor(x[i : i + 1]) for i in range(x.shape[0])], 0)
