"""prepare's worker processes (geoavatar.workers): ordered results, progress from the workers, an error in a
task raised in the parent with its own type, the same results inline and in workers; photometric segments."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from geoavatar.prep.errors import PrepareError
import numpy as np

from geoavatar.prep.segments import blend_weights, segment_rows, segments
from geoavatar.workers import WorkerPool, report_progress, split_range, worker_cache


def square_and_count(value: int) -> tuple[int, int]:
    """value squared, the process it ran in; counts 2 units of progress (a task of the tests below)."""
    report_progress(1)
    report_progress(1)
    return value * value, os.getpid()


def cached_once(_: int) -> int:
    calls = worker_cache("test-calls", list)  # made on the first call only
    calls.append(1)
    return len(calls)


def sleep_and_tell(folder: str) -> None:
    """Write this worker's pid into `folder`, then work for two minutes (a task whose parent is killed below)."""
    import time

    Path(folder, f"{os.getpid()}.pid").write_text("")
    time.sleep(120)


def fail_on_three(value: int) -> int:
    if value == 3:
        raise PrepareError(f"video 'x.mp4': frame {value} is unreadable")
    return value


def test_split_range_is_balanced_and_covers_everything():
    assert split_range(10, 3) == [(0, 3), (3, 7), (7, 10)]
    assert split_range(2, 5) == [(0, 1), (1, 2)]  # never an empty range
    assert split_range(0, 2) == []


def test_segments_have_balanced_cores_and_overlapping_fits():
    spans = segments(400, 300, 8)
    assert [(s.start, s.stop, s.fit_start, s.fit_stop) for s in spans] == [(0, 200, 0, 208), (200, 400, 192, 400)]
    assert [(s.start, s.stop) for s in segments(252, 300, 8)] == [(0, 252)]
    assert [(s.start, s.stop) for s in segments(252, 300, 8, min_parts=2)] == [(0, 126), (126, 252)]  # both cores
    assert len(segments(400, 300, 8, min_parts=2)) == 2 and len(segments(1, 300, 8, min_parts=2)) == 1
    spans = segments(5400, 300, 8)
    assert len(spans) == 18 and all(s.stop - s.start == 300 for s in spans) and spans[-1].stop == 5400
    # the written parameters pass from one fit to the next across the overlap: shares sum to 1 on every frame
    total, first = np.zeros(5400), None
    for span in spans:
        rows, core = segment_rows(span)
        weights = blend_weights(rows, core)
        total[rows] += weights
        first = weights if first is None else first
    np.testing.assert_allclose(total, 1.0)
    assert (first[:292] == 1).all() and np.all(np.diff(first[292:]) < 0) and first[-1] < 0.1  # ramps over 16 frames


@pytest.mark.parametrize("workers", [1, 2])
def test_results_in_order_with_progress(workers):
    counted: list[int] = []
    with WorkerPool(workers) as pool:
        results = pool.map(square_and_count, range(6), progress=counted.append)
    assert [value for value, _ in results] == [0, 1, 4, 9, 16, 25]
    assert sum(counted) == 12
    pids = {pid for _, pid in results}
    assert (pids == {os.getpid()}) if workers == 1 else (os.getpid() not in pids and 1 <= len(pids) <= 2)


def test_a_worker_keeps_its_cache_between_tasks():
    for _ in range(2):  # and a closed pool drops it (inline, the cache is this process's)
        with WorkerPool(1) as pool:
            assert pool.map(cached_once, range(3)) == [1, 2, 3]  # one list, made once, grown by each task


def test_an_error_in_a_worker_is_raised_here_with_its_type():
    with pytest.raises(PrepareError, match="frame 3 is unreadable"):
        with WorkerPool(2) as pool:
            pool.map(fail_on_three, range(6))
    assert pool._executor is None  # the workers were stopped


def test_bad_worker_count():
    with pytest.raises(ValueError, match="workers must be at least 1"):
        WorkerPool(0)


def _running(pid: int) -> bool:
    """True while `pid` exists and is not a zombie (an orphan that ended waits for a reaper that may never come)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc (Linux)")
def test_workers_end_when_their_parent_is_killed(tmp_path):
    """A parent killed outright (SIGKILL: no clean-up runs) leaves no worker computing: each ends itself."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from geoavatar.workers import WorkerPool\n"
        "from test_workers import sleep_and_tell\n"
        "if __name__ == '__main__':  # spawned workers import this script again\n"
        "    with WorkerPool(2) as pool:\n"
        f"        pool.map(sleep_and_tell, [{str(tmp_path)!r}] * 2)\n")
    parent = subprocess.Popen([sys.executable, str(script)])
    try:
        deadline = time.monotonic() + 120  # two spawned workers import torch first
        while len(list(tmp_path.glob("*.pid"))) < 2 and time.monotonic() < deadline and parent.poll() is None:
            time.sleep(0.2)
        pids = [int(path.stem) for path in tmp_path.glob("*.pid")]
        assert len(pids) == 2 and all(_running(pid) for pid in pids)
    finally:
        parent.kill()
        parent.wait()
    deadline = time.monotonic() + 15
    while any(_running(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_running(pid) for pid in pids)
