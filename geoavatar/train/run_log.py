"""RUN/train.log: timestamped lines of a training run, mirrored to TensorBoard when it is installed."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from geoavatar.train.checkpoint import LOG_FILE


class RunLog:
    """Appends timestamped lines to RUN/train.log (and mirrors scalars to RUN/tensorboard when importable)."""

    def __init__(self, run_dir: Path, echo: Callable[[str], None] | None = None):
        self.path = run_dir / LOG_FILE
        self.echo = echo
        self.tensorboard = None
        try:  # optional: only when the tensorboard package is installed
            from torch.utils.tensorboard import SummaryWriter

            self.tensorboard = SummaryWriter(str(run_dir / "tensorboard"))
        except Exception:  # noqa: BLE001 - not installed (the usual case): skip silently
            self.tensorboard = None

    def line(self, text: str, echo: bool = False) -> None:
        """Append `text` to the log; `echo` also shows it to the user (above the progress bar)."""
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        with open(self.path, "a", encoding="utf-8") as handle:
            handle.write(f"{stamp} {text}\n")
        if echo and self.echo is not None:
            self.echo(text)

    def scalars(self, step: int, values: dict[str, float]) -> None:
        if self.tensorboard is not None:
            for key, value in values.items():
                self.tensorboard.add_scalar(key, value, step)

    def close(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.close()


__all__ = ["RunLog"]
