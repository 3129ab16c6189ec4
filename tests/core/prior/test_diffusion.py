"""The diffusion prior is optional: without diffusers, a clear error naming what to install."""

from __future__ import annotations

import sys

import pytest

from pbrsr_core.errors import PriorUnavailable
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.registry import clear_cache, list_priors


def test_missing_diffusers_names_the_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "diffusers", None)  # import diffusers -> ImportError
    clear_cache()
    with pytest.raises(PriorUnavailable, match="pip install diffusers transformers"):
        load_prior(f"diffusion:{tmp_path}", "cpu")
    row = next(r for r in list_priors() if r["name"].startswith("diffusion"))
    assert row["scales"] == [4]


def test_listing_reports_diffusers_state():
    import importlib.util

    row = next(r for r in list_priors() if r["name"].startswith("diffusion"))
    assert row["installed"] == (importlib.util.find_spec("diffusers") is not None)
    if not row["installed"]:
        assert "pip install diffusers" in row["note"]
