"""Shared test set-up. Tests make their own procedural assets; none reads ../shared."""

from __future__ import annotations

import pytest
import torch

from pbrsr_core import runtime


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture
def set_runtime(monkeypatch):
    """``runtime.configure`` for one test: the settings in effect before come back after."""
    monkeypatch.setattr(runtime, "_current", runtime.current())
    return runtime.configure


@pytest.fixture
def gltf_validator() -> None:
    """The Khronos glTF-Validator (node + tools/npm, which scripts/setup installs): a test
    that asks for it fails without it, rather than pass unrun."""
    from pbrsr_core.asset.validator import validator_available

    if not validator_available():
        pytest.fail("node or the npm gltf-validator is missing: run ./scripts/setup")
