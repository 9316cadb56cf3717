"""Where a training run starts: a new run, a resumed one (`--resume`: its own configuration, checked against what the
options ask for) or an extended one (`--extend N`: the same run N steps longer). The resumed run's options take the
values it was trained with (dataset, resolution, test frames, seed, preset) unless given."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from geoavatar.config import TrainConfig, config_values
from geoavatar.train import checkpoint as ckpt
from geoavatar.train.options import RunOptions

DIFFERENCES_SHOWN = 6  # the resume refusal names at most this many differing fields


@dataclass
class RunStart:
    """What a run starts from: its configuration, the checkpoint it continues (None: a new run) and the record
    RUN/config.json keeps besides the configuration (overrides, schedule, extensions)."""

    config: TrainConfig
    payload: dict | None
    record: dict


def start_run(options: RunOptions, config: TrainConfig | None, resume: bool, extend: int,
              record: dict | None) -> RunStart:
    """The start of the run in options.out (options is completed in place for a resumed run); RunError when there is
    nothing to resume, or a run already where a new one should go, or the options contradict the run."""
    last_path = ckpt.run_checkpoint_path(options.out, "last")
    if resume or extend:
        return _resumed(options, config, extend, record, last_path)
    if last_path.exists():
        raise ckpt.RunError(f"{options.out}: already holds a run ({ckpt.CHECKPOINT_DIR}/{ckpt.LAST_CHECKPOINT}); pass "
                            "--resume to continue it, or choose a new --out")
    if config is None:
        raise ValueError("train: a TrainConfig is needed for a new run")
    record = dict(record or {})
    record.setdefault("overrides", {})
    return RunStart(config.validate(), None, record)


def _resumed(options: RunOptions, config: TrainConfig | None, extend: int, record: dict | None,
             last_path: Path) -> RunStart:
    if not last_path.is_file():
        if extend:
            raise ckpt.RunError(f"{options.out}: --extend continues a run, but there is none here "
                                f"(no {ckpt.CHECKPOINT_DIR}/{ckpt.LAST_CHECKPOINT})")
        raise ckpt.RunError(f"{options.out}: nothing to resume (no {ckpt.CHECKPOINT_DIR}/{ckpt.LAST_CHECKPOINT}); "
                            "start the run without --resume")
    payload = ckpt.load_checkpoint(last_path)
    saved = ckpt.config_from_json(payload["config"], f"{last_path} [config]")
    record = {**json.loads(payload.get("record", "{}")), **(record or {})}
    if extend:
        if config is not None:
            raise ValueError("train: extend continues the run's own configuration; pass config=None")
        config = saved.extended(extend)
        record["extensions"] = [*record.get("extensions", []), {
            "at_step": int(payload["step"]), "from_steps": saved.steps, "to_steps": config.steps}]
    else:
        check_resume_config(saved, config, str(last_path))
        config = saved
    adopt_saved_options(options, json.loads(payload.get("run", "{}")), last_path)
    record.setdefault("overrides", {})
    return RunStart(config.validate(), payload, record)


def check_resume_config(saved: TrainConfig, requested: TrainConfig | None, where: str) -> None:
    """RunError naming the differing fields when the options ask for another configuration than the run's own."""
    if requested is None or requested == saved:
        return
    flat_saved, flat_req = config_values(saved), config_values(requested)
    diffs = [f"{k}: run has {flat_saved.get(k)!r}, asked {flat_req.get(k)!r}"
             for k in sorted(set(flat_saved) | set(flat_req)) if flat_saved.get(k) != flat_req.get(k)]
    longer = ("; to train the run longer, use --extend N instead of --steps"
              if requested.steps != saved.steps else "")
    raise ckpt.RunError(f"{where}: --resume continues the run's own configuration, but the options ask for a "
                        f"different one ({'; '.join(diffs[:DIFFERENCES_SHOWN])}). Resume without those options, or "
                        f"train into a new --out{longer}.")


def adopt_saved_options(options: RunOptions, saved: dict, where: Path) -> None:
    """Fill in the options a resumed run keeps from its own (`saved`: the checkpoint's run options); RunError when
    the resolution asked differs or the run records no dataset."""
    if options.resolution is None:
        options.resolution = saved.get("resolution")
    elif options.resolution != saved.get("resolution"):
        raise ckpt.RunError(f"{where}: the run trained at --resolution {saved.get('resolution')}, "
                            f"asked {options.resolution}; resume without --resolution")
    if options.data is None:
        if not saved.get("data"):
            raise ckpt.RunError(f"{where}: the run does not record its dataset; pass --data")
        options.data = Path(saved["data"])
    if options.test_frames is None:
        options.test_frames = saved.get("test_frames")
    options.seed = int(saved.get("seed", options.seed))
    options.preset = options.preset or saved.get("preset")


__all__ = ["RunStart", "adopt_saved_options", "check_resume_config", "start_run"]
