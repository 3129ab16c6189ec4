"""Input limits, shared by the CLI and the API (the service fills them from settings)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

from .errors import InvalidAsset, LimitExceeded


@dataclass(frozen=True)
class Limits:
    max_file_bytes: int = 512 * 1024 * 1024  # one upload / input file
    max_triangles: int = 2_000_000
    max_texture_dim: int = 8192  # per side, of any input image
    max_output_dim: int = 16384  # per side, of any output image (input dim x scale)
    max_data_uri_bytes: int = 64 * 1024 * 1024
    max_zip_entries: int = 1000
    # sum of the sizes of the zip entries unpacked; also of the meshopt geometry decoded
    max_unpacked_bytes: int = 1024 * 1024 * 1024
    max_compression_ratio: float = 200.0  # size : compressed size, of each zip entry unpacked


class _Sized(Protocol):
    @property
    def index(self) -> int: ...
    @property
    def name(self) -> str: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...


def check_output_size(images: Iterable[_Sized], scales: Mapping[int, int], limits: Limits) -> None:
    """Refuse (LimitExceeded) an image whose side times its factor (``scales`` by image index)
    is over ``max_output_dim``."""
    for img in images:
        scale = scales[img.index]
        if max(img.width, img.height) * scale > limits.max_output_dim:
            raise LimitExceeded(
                f"image '{img.name}' is {img.width}x{img.height}; x{scale} would be "
                f"{img.width * scale}x{img.height * scale}, over the output limit of "
                f"{limits.max_output_dim} pixels per side (max_size caps it per map)"
            )


def check_image_size(w: int, h: int, name: str, limits: Limits) -> None:
    """Refuse an input image whose header declares an empty size (InvalidAsset) or a side
    over ``max_texture_dim`` (LimitExceeded), before any pixel is decoded."""
    if w <= 0 or h <= 0:
        raise InvalidAsset(f"the image '{name}' declares an empty size {w}x{h}")
    if w > limits.max_texture_dim or h > limits.max_texture_dim:
        raise LimitExceeded(
            f"the image '{name}' is {w}x{h}; the limit is {limits.max_texture_dim} per side"
        )
