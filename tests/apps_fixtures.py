"""Tiny subjects and runs for the application tests (test_apps, test_viewer): 48 px, a few frames,
a run of 2 training steps. Built once per test module."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

from geoavatar.config import preset
from geoavatar.data.splits import ShortVideoWarning
from geoavatar.data.synth.generate import SynthConfig, generate_dataset
from geoavatar.train.options import RunOptions
from geoavatar.train.trainer import train

SIZE = 48


def make_subject(out: Path, subject: int = 0, frames: int = 8, size: int = SIZE, seed: int = 0) -> Path:
    """A generated subject (VHAP layout, OpenHead parameters); the last 25 % of its frames are test frames."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        return generate_dataset(out, SynthConfig(subject=subject, frames=frames, size=size, seed=seed, workers=1),
                                progress=False)


def make_run(data: Path, out: Path, steps: int = 2) -> Path:
    """`geoavatar train` for `steps` steps of preset E (opacity 0.5 at the start so that the tiny head shows)."""
    config = preset("E", steps=steps)
    config = replace(config, model=replace(config.model, init_opacity=0.5))
    options = RunOptions(data=data, out=out, device="cpu", progress=False, val_every=10 * steps, ckpt_every=10 * steps)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        result = train(options, config)
    assert result.status == "finished", result
    return out


def make_untrained_run(data: Path, out: Path, **model) -> Path:
    """A RUN folder holding the trainer's step-0 state (one Gaussian per face): loads like any run, costs
    no rendering. For tests of the apps' plumbing that need no learned appearance. `model`: ModelConfig fields
    to change from preset E's."""
    from geoavatar.train import checkpoint as ckpt
    from geoavatar.train.checkpoint import state_payload
    from geoavatar.train.state import new_state, open_training_data

    config = preset("E", steps=2)
    config = replace(config, model=replace(config.model, **model))
    options = RunOptions(data=data, out=out, device="cpu", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        training_data = open_training_data(options, config)
    state = new_state(training_data, config, seed=0)
    ckpt.save_checkpoint(ckpt.run_checkpoint_path(out, "last"), state_payload(state, training_data, config, options))
    return out
