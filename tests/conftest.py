import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

from geoavatar.runtime import setup_process


def _user_build_cache() -> str | None:
    """The user's native build cache (geoavatar.native.cache_root) when it can be written, else None."""
    from geoavatar.native import cache_root

    root = cache_root()
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return str(root) if os.access(root, os.W_OK) else None


# Generated caches (OpenHead) go to one folder per test session, never the user's ~/.cache. Set at
# import time so module- and session-scoped fixtures see it too. The native extensions are the exception: their
# builds are keyed by everything that goes into them (geoavatar.native.build_key), so the suite uses the user's
# build cache, which `make install` fills, instead of compiling them again (a minute) in every session; a home
# that cannot be written leaves them in the session's folder. Read before GEOAVATAR_CACHE moves below.
if not os.environ.get("GEOAVATAR_EXT_CACHE"):
    user_builds = _user_build_cache()
    if user_builds:
        os.environ["GEOAVATAR_EXT_CACHE"] = user_builds
if os.environ.get("GEOAVATAR_TEST_CACHE"):
    os.environ["GEOAVATAR_CACHE"] = os.environ["GEOAVATAR_TEST_CACHE"]
else:
    os.environ["GEOAVATAR_CACHE"] = tempfile.mkdtemp(prefix="geoavatar-test-cache-")
    atexit.register(shutil.rmtree, os.environ["GEOAVATAR_CACHE"], ignore_errors=True)
setup_process()

# The real test videos (data/video/*.mp4) live in a folder beside the checkout, ../shared; a user's clone has none,
# and every test must then pass or skip with a reason. GEOAVATAR_SHARED names another folder (an empty one: a fresh
# clone, tests/test_fresh_clone.py). Tests reach it only through the helpers below, never by a path of their own
# (test_fresh_clone checks that too), so that the variable and the skip work everywhere.
SHARED = Path(os.environ.get("GEOAVATAR_SHARED") or Path(__file__).resolve().parents[1].parent / "shared").resolve()


def _video_path(name: str) -> Path:
    return SHARED / "data" / "video" / name


def _absent(path: Path) -> str:
    return f"shared test data {path} is absent (a clone without ../shared; GEOAVATAR_SHARED names the folder)"


def shared_video(name: str, required: bool = True) -> Path | None:
    """The shared test video `name` (e.g. "wojtek.mp4"). When it is absent: the calling test or fixture skipped with
    the reason, or None if not `required`. Call it inside a test or fixture, never at import."""
    path = _video_path(name)
    if path.is_file():
        return path
    if required:
        pytest.skip(_absent(path))
    return None


def needs_shared_video(*names: str) -> pytest.MarkDecorator:
    """A skipif mark for tests that need these shared test videos: it skips before their fixtures are built."""
    missing = [_video_path(name) for name in names if not _video_path(name).is_file()]
    return pytest.mark.skipif(bool(missing), reason=_absent(missing[0]) if missing else "")


def face_photo_video(path: Path, frames: int = 6, size: int = 256) -> Path:
    """A clip of a real face that needs no shared data: matplotlib's sample photograph (Grace Hopper, installed with
    it), a `size` px square of it moved one pixel per frame, 25 fps."""
    import matplotlib.cbook as cbook
    import numpy as np
    from PIL import Image

    from geoavatar.io.video import Mp4Writer

    photo = Image.open(cbook.get_sample_data("grace_hopper.jpg")).convert("RGB")  # 512 x 600, the face mid-image
    square = np.asarray(photo.resize((size, size * 600 // 512)))[size * 44 // 512:][:size]
    with Mp4Writer(path, fps=25) as video:
        for k in range(frames):
            video.write(np.ascontiguousarray(np.roll(square, k, axis=1)))
    return path


def pytest_report_header(config) -> str:
    videos = SHARED / "data" / "video"
    count = len(list(videos.glob("*.mp4"))) if videos.is_dir() else 0
    return f"shared test data: {SHARED} ({count} videos)" + ("" if count else "; the tests that need them skip")


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The shared data folder itself; tests that need it skip when it is absent."""
    if not SHARED.is_dir():
        pytest.skip(_absent(SHARED))
    return SHARED
