"""Process-wide runtime settings applied once by the CLI entry point (and the test suite), and the
`--device` option's meaning (`resolve_device`), shared by every command, and how third-party native libraries'
log lines are kept out of the terminal (`quiet_native_logs`; `--verbose` lets them through: `show_native_logs`).

glibc hands large blocks back to the OS and zero-fills them again on the next allocation; PyTorch on
CPU then runs 2-5x slower and noisily (measured on our 2-core machines, see DESIGN.md). Turning off
mmap for large blocks and raising the trim threshold keeps freed memory in the process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import threading
from contextlib import contextmanager

# mallopt parameter numbers from <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_THRESHOLD_BYTES = 64 * 1024**3

_applied = False


def apply_malloc_settings() -> bool:
    """Apply the glibc malloc settings to this process and to child processes.

    Returns True when mallopt was called (glibc present), False elsewhere (macOS, musl).
    """
    os.environ.setdefault("MALLOC_MMAP_MAX_", "0")
    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", str(_TRIM_THRESHOLD_BYTES))
    libc_name = ctypes.util.find_library("c")
    if libc_name is None:
        return False
    try:
        libc = ctypes.CDLL(libc_name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok_mmap = mallopt(_M_MMAP_MAX, 0) == 1
    # mallopt takes an int: clamp the threshold to INT_MAX (2 GiB) in-process.
    ok_trim = mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1
    return ok_mmap and ok_trim


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask on Linux)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def configure_threads() -> int:
    """Use every core the process may run on, unless GEOAVATAR_THREADS or OMP_NUM_THREADS says otherwise."""
    import torch

    env = os.environ.get("GEOAVATAR_THREADS") or os.environ.get("OMP_NUM_THREADS")
    threads = max(1, int(env)) if env else available_cores()
    torch.set_num_threads(threads)
    return threads


@contextmanager
def num_threads(threads: int):
    """Run a block with `threads` CPU threads for torch (and the native rasterizer, which reads torch's count);
    the previous count after it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def resolve_device(name: str):
    """The torch.device for a --device option: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.

    ValueError (naming the option) for a malformed name or CUDA asked for where there is none."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ValueError(f"--device: {err}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine (use --device cpu or auto)")
    return device


# --- third-party native logs ---------------------------------------------------------------------------------
#
# MediaPipe's C++ graphs (and the TensorFlow Lite inside them) write INFO / WARNING lines straight to file
# descriptor 2 through absl, glog and TFLite's own logger: "INFO: Created TensorFlow Lite XNNPACK delegate",
# "WARNING: All log messages before absl::InitializeLog() ...", "W0000 00:00:... inference_feedback_manager.cc",
# "... landmark_projection_calculator.cc". absl's level cannot be set from outside before absl::InitializeLog (which
# MediaPipe never calls), so the lines are kept out by pointing fd 2 at /dev/null around the calls that write them
# (a graph's start, its first frames); the environment variables below turn glog's and TensorFlow's own levels down
# where a library reads them, before it is loaded. GEOAVATAR_NATIVE_LOGS=1 (--verbose) lets everything
# through, in this process and in the worker processes it starts, which inherit the environment.

NATIVE_LOGS = "GEOAVATAR_NATIVE_LOGS"
_QUIET_LEVELS = {"GLOG_minloglevel": "2", "TF_CPP_MIN_LOG_LEVEL": "2"}  # errors only
_fd2_lock = threading.Lock()
_fd2_depth = 0
_fd2_saved: int | None = None


def native_logs_shown() -> bool:
    """Whether third-party native log lines reach the terminal (--verbose; GEOAVATAR_NATIVE_LOGS=1)."""
    return os.environ.get(NATIVE_LOGS, "0") not in ("", "0")


@contextmanager
def show_native_logs(shown: bool = True):
    """A block in which third-party native log lines reach the terminal when `shown` (--verbose), in this process and
    in the processes it starts (they inherit the environment); the setting before it afterwards. Without `shown` the
    block changes nothing."""
    if not shown:
        yield
        return
    before = os.environ.get(NATIVE_LOGS)
    os.environ[NATIVE_LOGS] = "1"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(NATIVE_LOGS, None)
        else:
            os.environ[NATIVE_LOGS] = before


def quiet_native_levels() -> None:
    """Before a native library that logs through glog or TensorFlow is loaded: its INFO and WARNING levels off,
    unless the logs are shown or the user set the variables."""
    if not native_logs_shown():
        for name, value in _QUIET_LEVELS.items():
            os.environ.setdefault(name, value)


@contextmanager
def quiet_native_logs():
    """A block whose writes to file descriptor 2 go to /dev/null, unless the native logs are shown: native code
    cannot be told otherwise. fd 2 belongs to the whole process, so another thread's stderr in the block is lost too:
    keep blocks short (a model's start). Python's buffered stderr is flushed first. Nests, from any thread."""
    global _fd2_depth, _fd2_saved
    if native_logs_shown():
        yield
        return
    with _fd2_lock:
        if _fd2_depth == 0:
            if sys.stderr is not None:
                try:
                    sys.stderr.flush()
                except (OSError, ValueError):
                    pass
            try:
                saved = os.dup(2)
            except OSError:  # no fd 2 at all: nothing to hide
                saved = None
            if saved is not None:
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, 2)
                os.close(devnull)
            _fd2_saved = saved
        _fd2_depth += 1
    try:
        yield
    finally:
        with _fd2_lock:
            _fd2_depth -= 1
            if _fd2_depth == 0 and _fd2_saved is not None:
                os.dup2(_fd2_saved, 2)
                os.close(_fd2_saved)
                _fd2_saved = None


def setup_process() -> None:
    """Malloc settings first (before large allocations), then threads. Idempotent."""
    global _applied
    if _applied:
        return
    apply_malloc_settings()
    configure_threads()
    _applied = True
