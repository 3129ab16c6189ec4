"""Shared test set-up. Tests make their own procedural assets; none reads ../shared."""

from __future__ import annotations

import os

import pytest
import torch

os.environ.setdefault("PBRSR_CACHE_DIR", os.path.join(os.path.dirname(__file__), "..", ".cache",
                                                      "pbrsr"))


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
