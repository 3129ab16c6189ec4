"""Input limits, shared by the CLI and the API (the service fills them from settings)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Limits:
    max_file_bytes: int = 512 * 1024 * 1024  # one upload / input file
    max_triangles: int = 2_000_000
    max_texture_dim: int = 8192  # per side, of any input image
    max_output_dim: int = 16384  # per side, of any output image (input dim x scale)
    max_data_uri_bytes: int = 64 * 1024 * 1024
    max_zip_entries: int = 1000
    max_unpacked_bytes: int = 1024 * 1024 * 1024  # sum of a zip's uncompressed sizes
