"""The base class of every error a user can cause, and the generic ones that belong to no layer.

`geoavatar <command>` prints a `GeoAvatarError` as one line, `geoavatar <command>: <message>`, and
exits with status 2; any other exception is a bug and keeps its traceback. So a message must stand on
its own: it names the file or option and says what is wrong (and, where it helps, what to do).

Layer errors derive from it: RunError (train/checkpoint.py), DatasetError (data/errors.py),
PrepareError (prep/errors.py), TrainingDiverged (train/trainer.py), ForbiddenPickleGlobal and
UnreadablePickle (io/safe_pickle.py), FlameFileNotFoundError and FlameFileError (head/flame.py),
MetricWeightsError (eval/weights.py; LPIPSWeightsError, eval/lpips.py, is one). Each keeps its older
built-in base (ValueError, RuntimeError, ...) so that code catching those still works.
"""

from __future__ import annotations

import errno


class GeoAvatarError(Exception):
    """A problem with the user's input, files, options or machine; the message is one line for them."""


def one_line(message: str) -> str:
    """A message as the one line the CLI prints (whitespace runs, newlines included, become one space)."""
    return " ".join(message.split()) or "failed (no message)"


class GeoAvatarWarning(UserWarning):
    """A note for the user that stops nothing (e.g. a stored run holds options removed since); the CLI prints it as
    one line, `geoavatar: note: <message>`."""


class OptionError(GeoAvatarError, ValueError):
    """A command-line option (or the argument that carries it) has a bad value; the message names it."""


class OutputPathError(GeoAvatarError, OSError):
    """A file cannot be written where it was asked (the path is a folder, a folder on its way is a file, or the
    folder is not writable); the message names the path."""


class DiskFullError(GeoAvatarError, OSError):
    """Writing a file failed because the disk (or the user's quota) is full; the message names the file.

    The writer has removed its temporary file, and the file it was replacing is unchanged."""

    def __init__(self, message: str, code: int = errno.ENOSPC, filename: str | None = None):
        super().__init__(message)  # one argument: str(err) is the message, not "[Errno 28] ..."
        self.errno = code
        self.filename = filename

    def __str__(self) -> str:  # OSError would print "[Errno 28] ..." once errno is set
        return str(self.args[0])


# errno values that mean "no room left": a full disk, or the user's quota used up
DISK_FULL_ERRNOS = frozenset(code for code in (errno.ENOSPC, getattr(errno, "EDQUOT", None)) if code is not None)


def is_disk_full(err: BaseException) -> bool:
    """True for an OSError saying the disk or the quota is full (PyAV's errors are OSErrors too)."""
    return isinstance(err, OSError) and not isinstance(err, DiskFullError) and err.errno in DISK_FULL_ERRNOS


def disk_full_error(path, err: OSError, what: str = "") -> DiskFullError:
    """DiskFullError for `err` while writing `path`; `what` adds what is left (e.g. 'the previous file is unchanged')."""
    reason = "the disk quota is exceeded" if err.errno != errno.ENOSPC else "the disk is full"
    message = f"{path}: cannot write it, {reason} (free some space and run again)"
    return DiskFullError(message + (f"; {what}" if what else ""), err.errno, str(path))


__all__ = ["DISK_FULL_ERRNOS", "DiskFullError", "GeoAvatarError", "GeoAvatarWarning", "OptionError", "OutputPathError",
           "disk_full_error", "is_disk_full", "one_line"]
