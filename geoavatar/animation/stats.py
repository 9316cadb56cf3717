"""What a live play measured (`geoavatar drive`'s summary and status line): a live source counts what it took,
fitted and dropped; play counts what the sinks showed, each frame's stage times and its latency."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

import numpy as np

STAGES = ("landmarks", "fit", "pose", "render")  # the live tracker's two stages, then play's and its sinks'


@dataclass
class DriveStats:
    frames: int = 0  # frames shown after the first online one (the FPS counts these)
    processed: int = 0  # frames the fit stage took from the source (identity stage included)
    init_frames: int = 0
    dropped: int = 0  # frames the source delivered that were never processed
    delivered: int = 0
    no_face: int = 0
    seconds: float = 0.0  # wall time from the first online frame to the last
    init_seconds: float = 0.0  # the identity stage's fit
    stage_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    latency_ms: list[float] = field(default_factory=list)
    records: list[dict] = field(default_factory=list)  # per processed frame (record=True)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        stages = " ".join(f"{s} {np.mean(v):.1f}" for s, v in self.stage_ms.items() if v)
        latency = f"{np.median(self.latency_ms):.0f} ms" if self.latency_ms else "-"
        return (f"{self.frames} frames, {self.fps:.1f} fps, dropped {self.dropped}/{self.delivered}, latency {latency} "
                f"(median), stages ms: {stages}")


class LiveStatus:
    """The status line on stderr (FPS, drops, latency, recent stage times), at most once every `every` seconds; on a
    terminal it rewrites one line."""

    def __init__(self, enabled: bool, every: float = 1.0, label: str = "drive"):
        self.enabled, self.every, self.last, self.label = enabled, every, 0.0, label
        self.tty = sys.stderr.isatty()

    def __call__(self, stats: DriveStats, force: bool = False) -> None:
        now = time.perf_counter()
        if not self.enabled or (now - self.last < self.every and not force):
            return
        self.last = now
        recent = {s: np.mean(v[-25:]) for s, v in stats.stage_ms.items() if v}
        line = (f"{self.label}: {stats.frames} frames, {stats.fps:5.1f} fps, dropped {stats.dropped}, latency "
                f"{np.mean(stats.latency_ms[-25:]) if stats.latency_ms else 0:5.0f} ms | "
                + " ".join(f"{s} {v:5.1f}" for s, v in recent.items()) + " ms")
        print(("\r" + line) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def end(self, stats: DriveStats) -> None:
        """The last line, whatever the time since the one before; a terminal's line ended."""
        self(stats, force=True)
        if self.enabled and self.tty:
            print(file=sys.stderr)


__all__ = ["DriveStats", "LiveStatus", "STAGES"]
