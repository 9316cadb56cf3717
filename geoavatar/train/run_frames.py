"""A trained run's frames: which head parameters and which T render a timestep (the one place that decides).

    frames = RunFrames(run)                             # the run's per-timestep parameters, on its device
    params, T = frames.params(timestep)                 # HeadParams (per-frame keys [1, ...]) and the deformer's T
    params, T = frames.params(timestep, tracked)        # a dataset frame: its own tracked parameters unless trained

The rule: a training timestep renders with the run's refined parameters and its own T, which reproduces what
training saw; any other timestep (test frames, the novel split's views of them) renders with T = 0 (None), the
paper's inference setting, since gamma(T) was never trained there (avatar.frame_timestep; `mode` overrides the T
rule as `geoavatar eval`'s timestep_mode does), and with: the run's held-out fit when train fitted the frame
against the finished avatar (train/held_out_fit.py) and the caller's frame comes from the run's own dataset (or the
caller has none); else the parameters the caller's dataset holds for it (eval with another copy, e.g. `geoavatar
track --avatar`'s); else the run's stored row (the dataset's, which training never refines for a frame it does
not render, train/frame_params.py).

Naming (docs/ARCHITECTURE.md, "A frame's identity"): a `timestep` is the frame's number in its video, its `row`
the row of the per-timestep parameter tensors [T, ...] (row i = timesteps[i]).
"""

from __future__ import annotations

from pathlib import Path

from torch import Tensor

from geoavatar.avatar import TimestepMode, frame_timestep
from geoavatar.errors import OptionError
from geoavatar.head.params import SUBJECT_KEYS, HeadParams
from geoavatar.train.checkpoint import LoadedRun, RunError


TRACKED_COPY_REPORT = "track.json"  # what `geoavatar track` writes into a copy of a dataset (apps/track.py)


class RunFrames:
    """The per-timestep head parameters of a run (refined for training frames) and the T rule."""

    def __init__(self, run: LoadedRun):
        self.run = run
        self.device = run.device
        self.timesteps: list[int] = list(run.info.timesteps["all"])
        self.trained: set[int] = set(run.info.timesteps.get("train", []))
        self.fitted: set[int] = set(run.info.held_out)  # held-out timesteps fitted against the finished avatar
        self._row = {t: i for i, t in enumerate(self.timesteps)}
        self.values = HeadParams.from_npz(run.info.frame_params).to(self.device)  # [T, ...]; shape [S]
        rows = self.values.batch
        if rows != len(self.timesteps):
            raise RunError(f"{run.info.checkpoint}: parameters of {rows} frames for {len(self.timesteps)} timesteps")

    def __len__(self) -> int:
        return len(self.timesteps)

    def resolve(self, timestep: int | None) -> int:
        """`timestep` (None: the first one) checked against the run's timesteps."""
        if timestep is None:
            return self.timesteps[0]
        if timestep not in self._row:
            lo, hi = self.timesteps[0], self.timesteps[-1]
            raise OptionError(f"--frame {timestep}: not a timestep of the run's dataset ({len(self)} frames, {lo}..{hi})")
        return int(timestep)

    def row(self, timestep: int) -> int:
        """The row of `timestep` in the per-timestep parameters."""
        return self._row[self.resolve(timestep)]

    def params(self, timestep: int, tracked: HeadParams | None = None, mode: TimestepMode = "auto",
               own_dataset: bool = True) -> tuple[HeadParams, int | None]:
        """(HeadParams of a timestep, per-frame keys [1, ...]; its T, None = T = 0): the run's refined row for a
        training timestep and its held-out fit for a fitted one (`tracked` from the run's own dataset), else
        `tracked` (a dataset's parameters for the frame) or, without it, the run's row."""
        timestep = self.resolve(timestep)
        from_run = timestep in self.trained or (timestep in self.fitted and own_dataset) or tracked is None
        params = self.values.frame(self._row[timestep]) if from_run else tracked
        return params, frame_timestep(timestep, self.trained, mode)

    def is_own_dataset(self, root) -> bool:
        """Whether the dataset folder `root` is the run's own (is_own_dataset)."""
        return is_own_dataset(self.run.info.data_root, root)

    def identity(self) -> dict[str, Tensor]:
        """The subject keys (shape [S], static_offset [1, V, 3] when present): the avatar's identity."""
        return {k: v for k, v in self.values.to_npz().items() if k in SUBJECT_KEYS}


def is_own_dataset(recorded, root) -> bool:
    """Whether the dataset folder `root` is a run's own, whose recorded folder is `recorded`: that folder, or any
    folder but a tracked copy once that one is gone (a moved dataset); else another copy (e.g. `geoavatar track
    --avatar`'s, which holds its track.json)."""
    if Path(root).resolve() == Path(recorded).resolve():
        return True
    return not Path(recorded).is_dir() and not (Path(root) / TRACKED_COPY_REPORT).is_file()


__all__ = ["RunFrames", "TRACKED_COPY_REPORT", "is_own_dataset"]
