"""Fixtures shared by the service tests."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.app import create_app


@pytest.fixture
def client(settings):
    """A TestClient of the app built from the test module's ``settings`` fixture; answers as
    the server would (problem bodies, no exceptions raised)."""
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c
