"""Shared test set-up. Tests make their own procedural assets; none reads ../shared."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
