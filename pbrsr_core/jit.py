"""The keyword options the numba kernels share (``@numba.njit(**options)``), typed so that the
call checks against numba's stubs."""

from __future__ import annotations

from typing import Literal, TypedDict


class JitOptions(TypedDict, total=False):
    cache: bool
    parallel: bool
    fastmath: bool | set[str]
    error_model: Literal["python", "numpy"]
    inline: Literal["never", "always"]
