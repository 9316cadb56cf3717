import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

from geoavatar.runtime import setup_process

# Generated caches (OpenHead) go to one folder per test session, never the user's ~/.cache. Set at
# import time so module- and session-scoped fixtures see it too.
if os.environ.get("GEOAVATAR_TEST_CACHE"):
    os.environ["GEOAVATAR_CACHE"] = os.environ["GEOAVATAR_TEST_CACHE"]
else:
    os.environ["GEOAVATAR_CACHE"] = tempfile.mkdtemp(prefix="geoavatar-test-cache-")
    atexit.register(shutil.rmtree, os.environ["GEOAVATAR_CACHE"], ignore_errors=True)
setup_process()

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """../shared beside the checkout (real videos); tests that need it skip when it is absent."""
    if not SHARED.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED}")
    return SHARED
