"""The ``PBRSR_*`` variables that tune the core at run time, read once by an entry point.

The core itself never reads the environment (:mod:`pbrsr_core.runtime`); the ``pbrsr`` CLI,
the service and the worker call :func:`configure_from_env` at start-up.

| variable | runtime field |
|---|---|
| ``PBRSR_CACHE_DIR`` (else ``$XDG_CACHE_HOME/pbrsr``) | ``cache_dir`` |
| ``PBRSR_NPM_DIR`` | ``npm_dir`` |
| ``PBRSR_PRIOR_TILE`` | ``prior_tile`` |
| ``PBRSR_PRIOR_PRECISION`` | ``prior_precision`` |
| ``PBRSR_PSEUDO_GT_CACHE_MB`` | ``pseudo_gt_cache_mb`` |
| ``PBRSR_SHADE_REFERENCE`` (``1``: on) | ``shade_reference`` |
| ``PBRSR_KERNEL_CLASSIFIER`` (a file of ``pbrsr kernel fit``) | ``kernel_classifier`` |
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .. import runtime
from ..errors import InvalidOptions
from ..runtime import PRECISIONS


def _integer(environ: Mapping[str, str], name: str, low: int, wrong: str) -> int:
    """``environ[name]`` as an integer of at least ``low`` (``wrong`` says what else it is)."""
    value = environ[name].strip()
    try:
        number = int(value)
    except ValueError:
        raise InvalidOptions(f"{name}={value!r} is not a whole number") from None
    if number < low:
        raise InvalidOptions(f"{name}={number} {wrong}")
    return number


def runtime_changes(environ: Mapping[str, str]) -> dict[str, Any]:
    """The runtime fields the variables in ``environ`` set (unset or empty ones: none)."""
    env = {k: v for k, v in environ.items() if k.startswith(("PBRSR_", "XDG_")) and v.strip()}
    changes: dict[str, Any] = {}
    if "PBRSR_CACHE_DIR" in env:
        changes["cache_dir"] = Path(env["PBRSR_CACHE_DIR"]).expanduser()
    elif "XDG_CACHE_HOME" in env:
        changes["cache_dir"] = Path(env["XDG_CACHE_HOME"]).expanduser() / "pbrsr"
    if "PBRSR_NPM_DIR" in env:
        changes["npm_dir"] = Path(env["PBRSR_NPM_DIR"]).expanduser()
    if "PBRSR_PRIOR_TILE" in env:
        changes["prior_tile"] = _integer(env, "PBRSR_PRIOR_TILE", 1, "is not a positive tile side")
    if "PBRSR_PRIOR_PRECISION" in env:
        precision = env["PBRSR_PRIOR_PRECISION"].strip()
        if precision not in PRECISIONS:
            raise InvalidOptions(
                f"PBRSR_PRIOR_PRECISION={precision!r} is not one of {', '.join(PRECISIONS)}"
            )
        changes["prior_precision"] = precision
    if "PBRSR_PSEUDO_GT_CACHE_MB" in env:
        changes["pseudo_gt_cache_mb"] = _integer(env, "PBRSR_PSEUDO_GT_CACHE_MB", 0, "is negative")
    if "PBRSR_SHADE_REFERENCE" in env:
        changes["shade_reference"] = env["PBRSR_SHADE_REFERENCE"].strip() != "0"
    if "PBRSR_KERNEL_CLASSIFIER" in env:
        path = Path(env["PBRSR_KERNEL_CLASSIFIER"].strip()).expanduser()
        if not path.is_file():
            raise InvalidOptions(f"PBRSR_KERNEL_CLASSIFIER={str(path)!r} is not a file")
        changes["kernel_classifier"] = path
    return changes


def configure_from_env(environ: Mapping[str, str] | None = None) -> runtime.Runtime:
    """Install the runtime settings the environment (default ``os.environ``) names."""
    return runtime.configure(**runtime_changes(os.environ if environ is None else environ))
