"""Worker processes for `prepare`'s stages and `train`'s held-out fit: both cores busy without threads fighting inside one
process.

    with WorkerPool(workers=2) as pool:                      # spawned on first use, once per prepare run
        results = pool.map(function, tasks, progress=bar.update)      # ordered; function(task) in a worker
        for result in pool.imap(function, tasks, window=4): ...       # ordered, at most `window` in flight

Each stage splits its frames into tasks (frame ranges, photometric segments) whose results do not depend on
how many workers run them, so a dataset is the same on 1 core or 16. Workers are *spawned* (never forked:
the parent has MediaPipe's and OpenMP's threads running, and a forked copy of a locked mutex deadlocks), run
one torch thread each (the stages' tensors are small: on our 2-core machines two threads in one process made
the photometric stage 26x slower, BENCHMARKS.md) and keep per-process state (`worker_cache`: a head model,
a face detector) between tasks. With workers == 1 every task runs inline, in this process, one thread.

Progress: a task calls `report_progress(n)`; from a worker the counts travel over a queue and the parent
passes them to `progress` while it waits. An exception in a task is raised in the parent; the pool's workers
are then ended (every worker process, without waiting on them), so a failed run does not leave them computing; a
worker whose parent was killed outright ends itself within a second (_exit_when_orphaned).
"""

from __future__ import annotations

import os
import queue as queue_module
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any, Callable, Iterable, Iterator

from geoavatar.runtime import available_cores

_progress_queue = None  # in a worker: the queue progress counts go to
_inline_progress: Callable[[int], None] | None = None  # inline (workers == 1): the callback itself
_cache: dict[str, Any] = {}  # per-process state of the tasks (worker_cache)
_HELLO = "pid"


def default_workers() -> int:
    """Worker processes for prepare: the cores this process may use, at most 8 (each holds up to ~0.9 GB)."""
    return max(1, min(8, available_cores()))


def report_progress(count: int) -> None:
    """Count `count` units of work done (called by a task, in a worker or inline)."""
    if _progress_queue is not None:
        _progress_queue.put(count)
    elif _inline_progress is not None:
        _inline_progress(count)


def worker_cache(key: str, make: Callable[[], Any]) -> Any:
    """`make()` once per process under `key` (a model every task of a worker reuses)."""
    if key not in _cache:
        _cache[key] = make()
    return _cache[key]


# Seconds between a worker's checks that the process that started it is still there.
PARENT_CHECK_SECONDS = 1.0


def _exit_when_orphaned(parent: int) -> None:
    """End this worker once its parent is gone (re-parented: getppid changes). A parent killed by a signal it cannot
    handle (SIGTERM from a batch system, SIGKILL, an OOM kill) runs no clean-up, and its workers would otherwise go on
    computing the rest of their task on both cores (measured: two orphans of a killed `prepare` at ~20 % CPU each for
    18 minutes, slowing the next job)."""
    import threading
    import time

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="geoavatar-parent-watch", daemon=True).start()


def _start_worker(progress_queue, parent: int) -> None:
    global _progress_queue
    from geoavatar.runtime import apply_malloc_settings

    _exit_when_orphaned(parent)
    apply_malloc_settings()
    import torch

    torch.set_num_threads(1)
    _progress_queue = progress_queue
    progress_queue.put((_HELLO, os.getpid()))


def split_range(count: int, parts: int) -> list[tuple[int, int]]:
    """`parts` contiguous, balanced (start, stop) ranges covering range(count) (no empty one)."""
    parts = max(1, min(parts, count))
    bounds = [round(k * count / parts) for k in range(parts + 1)]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


class WorkerPool:
    """Processes that run a prepare run's tasks; see the module docstring."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.workers = workers
        self._executor: ProcessPoolExecutor | None = None
        self._queue = None
        self._pids: set[int] = set()

    def _start(self) -> ProcessPoolExecutor:
        if self._executor is None:
            import multiprocessing

            context = multiprocessing.get_context("spawn")
            self._queue = context.Queue()
            self._executor = ProcessPoolExecutor(self.workers, mp_context=context, initializer=_start_worker,
                                                 initargs=(self._queue, os.getpid()))
        return self._executor

    def map(self, function: Callable, tasks: Iterable, progress: Callable[[int], None] | None = None) -> list:
        """[function(task) for task in tasks], run in the workers (inline with one worker)."""
        return list(self.imap(function, tasks, progress))

    def imap(self, function: Callable, tasks: Iterable, progress: Callable[[int], None] | None = None,
             window: int | None = None) -> Iterator:
        """function(task) for each task, yielded in order; at most `window` tasks (default: all) submitted ahead."""
        tasks = list(tasks)
        if self.workers == 1:  # a single task still goes to a worker: this process's memory stays small
            yield from self._inline(function, tasks, progress)
            return
        executor = self._start()
        pending: deque[Future] = deque()
        ahead = window or len(tasks)
        index = 0
        try:
            while index < len(tasks) or pending:
                while index < len(tasks) and len(pending) < ahead:
                    pending.append(executor.submit(function, tasks[index]))
                    index += 1
                while not pending[0].done():
                    wait([pending[0]], timeout=0.1, return_when=FIRST_COMPLETED)
                    self._drain(progress)
                self._drain(progress)
                yield pending.popleft().result()
        except BaseException:  # a task failed, Ctrl-C, or the caller stopped early: end the tasks still out
            if pending or index < len(tasks):
                for future in pending:
                    future.cancel()
                self.close(stop=True)
            raise

    def _inline(self, function: Callable, tasks: list, progress) -> Iterator:
        global _inline_progress
        from geoavatar.runtime import num_threads

        for task in tasks:
            _inline_progress = progress
            try:
                with num_threads(1):
                    result = function(task)
            finally:
                _inline_progress = None
            yield result

    def _drain(self, progress) -> None:
        while True:
            try:
                item = self._queue.get_nowait()
            except queue_module.Empty:
                return
            if isinstance(item, tuple) and item[0] == _HELLO:
                self._pids.add(item[1])
            elif progress is not None:
                progress(item)

    def cpu_seconds(self) -> float:
        """CPU time (user + system) the live workers have used so far (read from /proc; 0 where there is none).
        A worker's time is counted while it lives: read it before `close`."""
        if self._executor is None:
            return 0.0
        self._drain(None)
        total = 0.0
        for pid in self._pids:
            try:
                with open(f"/proc/{pid}/stat") as stat:
                    fields = stat.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime
        return total

    def close(self, stop: bool = False) -> None:
        """Shut the workers down; `stop`: end them now (by their process ids), running tasks included. The state
        inline tasks cached in this process goes too."""
        _cache.clear()
        if self._executor is None:
            return
        if stop:
            # Every worker process, whether or not its hello was read: one killed while it held the progress
            # queue's lock would leave the others blocked on it, and a wait for them would never end.
            processes = list((getattr(self._executor, "_processes", None) or {}).values())
            for process in processes:
                process.terminate()
            for process in processes:
                process.join(timeout=10)
                if process.is_alive():
                    process.kill()
        self._executor.shutdown(wait=not stop, cancel_futures=True)
        self._executor, self._pids = None, set()
        self._queue.close()
        self._queue = None

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(stop=exc_type is not None)


__all__ = ["WorkerPool", "default_workers", "report_progress", "split_range", "worker_cache"]
