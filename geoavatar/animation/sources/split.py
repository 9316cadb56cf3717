"""A run's own frames as a source: each timestep with its parameters and T (RunFrames' T rule: a training frame with
its refined parameters and its own T, any other with the tracked parameters and T = 0). `export --format web
--split` and `view`'s clip play it."""

from __future__ import annotations

from typing import Iterator

from geoavatar.animation.frames import AnimationFrame
from geoavatar.train.checkpoint import LoadedRun
from geoavatar.train.run_frames import RunFrames


class SplitFrames:
    """Source: `timesteps` of a run (a split's, or any), in that order, at `fps`."""

    live = False
    audio = None

    def __init__(self, run: LoadedRun, timesteps: list[int], fps: float = 25.0, frames: RunFrames | None = None):
        self.frames = frames if frames is not None else RunFrames(run)
        self.timesteps, self.fps = list(timesteps), fps

    def __len__(self) -> int:
        return len(self.timesteps)

    def __iter__(self) -> Iterator[AnimationFrame]:
        for index, timestep in enumerate(self.timesteps):
            params, T = self.frames.params(timestep)
            yield AnimationFrame(index, params, T, timestep=timestep)

    def close(self) -> None:
        pass


__all__ = ["SplitFrames"]
