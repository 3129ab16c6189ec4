"""``pbrsr priors calibrate``: measure the int8 activation quantization of a set's SRMD
networks on training crops and store it in each weights file (:mod:`pbrsr_core.prior.int8`),
then score float32 and int8 side by side on the held-out materials."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ...errors import InvalidOptions
from ..int8 import METADATA_KEY, Int8SRMD, calibrate
from ..srmd import SRMD
from ..texture import weight_files
from .data import Material
from .loop import INT8_CALIBRATION_CROPS, Validator, calibration_crops
from .weights import load_network, update_metadata

PATCH = 256
"""HR crop side (x4: crops of 64² LR pixels), and of the held-out crops scored."""


@dataclass(frozen=True)
class Calibrated:
    file: Path
    kind: str
    fp32: float
    """Held-out PSNR (dB) in float32."""
    int8: float
    """Held-out PSNR (dB) in int8."""


def srmd_files(source: Path) -> dict[Path, tuple[str, ...]]:
    """The SRMD weights files of a set (folder or file) -> the map kinds each serves."""
    out: dict[Path, tuple[str, ...]] = {}
    for (kind, _, _), f in weight_files(source).items():
        if isinstance(load_network(f), SRMD):
            out[f] = (*out.get(f, ()), kind)
    if not out:
        raise InvalidOptions(f"'{source}' holds no SRMD network to calibrate")
    return out


def calibrate_set(
    source: Path,
    train: list[Material],
    held: list[Material],
    *,
    crops: int = INT8_CALIBRATION_CROPS,
    patch: int = PATCH,
    command: str = "",
) -> list[Calibrated]:
    """Calibrate every SRMD network of ``source`` on ``crops`` crops of ``train`` (``patch``
    pixels, HR; the kinds of a shared network in turn, half of them drawn), store the result
    in its file and score it on ``held`` (crops of ``patch``), per kind."""
    if crops < 1:
        raise InvalidOptions(f"--crops must be positive, not {crops}")
    out: list[Calibrated] = []
    for path, kinds in srmd_files(source).items():
        net = load_network(path)
        assert isinstance(net, SRMD)
        lr = calibration_crops(train, kinds, net.stride, patch, crops, 1)
        calibration = calibrate(net, lr, source=command)
        validator = Validator(held, kinds, net.stride, patch)
        fp32 = validator(net)
        int8 = validator(Int8SRMD(net, calibration))
        update_metadata(path, {METADATA_KEY: calibration.to_json()})
        out.extend(Calibrated(path, k, fp32[k], int8[k]) for k in fp32)
    return out
