"""Image SR priors: ``load_prior(name, device)`` and the :class:`Prior` interface.

See ``docs/ARCHITECTURE.md`` (priors section) for the names, settings and the direct-prior
map helpers in :mod:`pbrsr_core.prior.direct`.
"""

from .base import Prior
from .registry import DEFAULT_PRIOR, check_name, clear_cache, load_prior

__all__ = ["DEFAULT_PRIOR", "Prior", "check_name", "clear_cache", "load_prior"]
