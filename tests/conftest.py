import os
from pathlib import Path

import pytest

from geoavatar.runtime import setup_process

setup_process()

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """../shared beside the checkout (real videos); tests that need it skip when it is absent."""
    if not SHARED.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED}")
    return SHARED


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path_factory, monkeypatch):
    """Keep generated caches (OpenHead) out of the user's home: one cache for the whole session."""
    cache = tmp_path_factory.getbasetemp() / "geoavatar-cache"
    monkeypatch.setenv("GEOAVATAR_CACHE", os.environ.get("GEOAVATAR_TEST_CACHE", str(cache)))
