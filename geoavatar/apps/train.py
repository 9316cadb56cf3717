"""`geoavatar train`: train an avatar on a tracked monocular video (VHAP layout or INSTA).

The command's options are one dataclass, TrainArgs, which tyro parses: the run options (the fields of
RunOptions, flattened: --out, --data, --preset, --resolution, ...), the length of the run (--steps or
--minutes, --extend, --resume) and the whole TrainConfig under --config.*, whose defaults are the
values of the chosen --preset (`geoavatar train --preset A --help` shows A's).

Steps and the schedule: the presets hold the paper's 200k-step schedule and `TrainConfig.scaled_to`
scales every step-based milestone to the run's --steps. A milestone set on the command line
(--config.aps-step, --config.densify.start/stop/every/reset-opacity-every,
--config.lr.position-decay-steps) is a step of this run and is not scaled.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, Optional, Sequence

import tyro

from geoavatar.config import (ABLATIONS, CPU_RESOLUTION, CPU_STEPS, DEFAULT_PRESET, PAPER_STEPS, STEP_FIELDS,
                              TrainConfig, config_values, preset as make_preset, with_values)
from geoavatar.data.splits import ShortVideoWarning
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.train.held_out_fit import MAX_FRAMES
from geoavatar.train.options import RunOptions
from geoavatar.train.trainer import train as run_training

if TYPE_CHECKING:
    from geoavatar.train.budget import BudgetPlan


@dataclass
class CommandLineConfig(TrainConfig):
    """Defaults: the --preset's values (the paper's, on its 200k-step schedule). Step-based fields set
    here are steps of this run and do not scale with --steps; those left alone scale."""

    steps: Annotated[int, tyro.conf.Suppress] = PAPER_STEPS  # set by --steps / --minutes


@dataclass
class TrainArgs:
    """Train a GeoAvatar avatar from a tracked video into the folder OUT.

    Writes OUT/config.json (the full configuration, the options given on the command line and how the
    steps were chosen), OUT/checkpoints/last.pt (every --ckpt-every steps, on Ctrl-C and at the end) and
    final.pt, OUT/aps.json, OUT/train.log and OUT/val/step_XXXXXX.png (ground truth | render). Ctrl-C
    stops after the current step and saves; --resume continues exactly where the run stopped; --extend N
    trains a finished run N steps longer. Every step-based milestone (APS at half of the run,
    densification, opacity resets, learning-rate decay) scales with --steps, so short CPU runs keep the
    paper's proportions; a milestone set with --config.* is a step of this run and stays put.
    """

    run: Annotated[RunOptions, tyro.conf.arg(name="", prefix_name=False)]
    # The budget of a new run given neither --steps nor --minutes (default auto): auto = on CUDA the
    # paper's 200000 steps at the stored size, on CPU 3000 steps at 256 px (about 5 minutes on 2 cores
    # for a 300-frame video; the best held-out score we measured on our test videos);
    # paper = the paper's 200000 steps at the stored size on any device (days on a CPU).
    schedule: Optional[Literal["auto", "paper"]] = None
    # Training steps (default: chosen by --schedule for a new run; with --resume the run's own).
    steps: Optional[int] = None
    # Time budget of a new run, instead of --steps: a warm-up on a throwaway copy times a few steps at the
    # initial Gaussian count and at 4x it; assuming the count grows to 4.5x over densification (as in our
    # runs), the steps that fit are chosen, printed with the estimated end time and recorded in
    # config.json. The run equals --steps with that number.
    minutes: Optional[float] = None
    # Train the run in OUT this many steps longer (no --resume needed): it continues from its last step
    # with every milestone where it was, so the added steps run at the final learning rates with no new
    # densification, opacity reset or APS. An interrupted extension continues with --resume.
    extend: Optional[int] = None
    # Continue the run in OUT from OUT/checkpoints/last.pt, exactly (its own configuration).
    resume: bool = False
    # The whole training configuration, e.g. --config.loss.lambda-angle 0.02. Defaults: the --preset's
    # values on the paper's 200k-step schedule. Step-based fields (aps-step, densify.start/stop/every/
    # reset-opacity-every, lr.position-decay-steps) scale with --steps unless set here: a value set here is
    # a step of this run.
    config: CommandLineConfig = field(default_factory=CommandLineConfig)
    # At the end, fit the held-out (test) frames' head parameters against the finished avatar, as training fitted
    # its own frames' (RUN/held_out.npz; eval and every command then render them so). The avatar never sees their
    # pixels while it learns. --no-held-out-fit keeps the tracker's parameters for them.
    held_out_fit: bool = True
    # The held-out frames that fit fits at most (0: all). A longer test split is fitted in runs of neighbouring
    # frames spread evenly over it, and eval scores those runs; the frames between them render with the tracker's
    # parameters plus their fitted neighbours' correction. The default fits a 12-s video's ~70 held-out frames all,
    # and bounds the fit's time on a long video (train/held_out_fit.py).
    held_out_frames: int = MAX_FRAMES
    # Also learn the voice model when the dataset has speech (geoavatar voice; RUN/voice/): sound -> face, from the
    # training frames only. --no-voice skips it.
    voice: bool = True
    # Dotted names of the `config` fields given on the command line (parse_args fills it): only those
    # are taken from `config`, every other field from the preset (or from the run, with --resume).
    overrides: Annotated[tuple[str, ...], tyro.conf.Suppress] = ()


def parse_args(argv: Sequence[str], prog: str = "geoavatar train") -> TrainArgs:
    """TrainArgs from command-line words; the --config.* defaults are those of the --preset given."""
    argv = list(argv)
    _refuse_removed_options(argv)
    name = _option_value(argv, "--preset")
    defaults = make_preset(name if name in ABLATIONS else DEFAULT_PRESET)
    default = TrainArgs(run=RunOptions(out=tyro.MISSING),
                        config=CommandLineConfig(**{f.name: getattr(defaults, f.name) for f in fields(TrainConfig)}))
    args = tyro.cli(TrainArgs, args=argv, prog=prog, default=default)
    args.overrides = config_options_given(argv)
    return args


def _option_value(argv: list[str], option: str) -> str | None:
    """The value of the last `option VALUE` / `option=VALUE` among the words, else None."""
    value = None
    for i, word in enumerate(argv):
        if word == option and i + 1 < len(argv):
            value = argv[i + 1]
        elif word.startswith(option + "="):
            value = word.split("=", 1)[1]
    return value


def _refuse_removed_options(argv: list[str]) -> None:
    """OptionError naming a --config.* option that was removed (measured and rejected), instead of tyro's
    'unrecognized option'."""
    from geoavatar.train.checkpoint import FIELDS_REMOVED

    for word in argv:
        if not word.startswith("--config."):
            continue
        option = word.split("=", 1)[0]
        name = option[len("--config."):].replace("-", "_")
        head, _, last = name.rpartition(".")
        if name in FIELDS_REMOVED or (last.startswith("no_") and f"{head}.{last[3:]}" in FIELDS_REMOVED):
            raise OptionError(f"{option} was removed: measured and rejected (docs/REJECTED.md)")


def config_options_given(argv: Sequence[str]) -> tuple[str, ...]:
    """Dotted TrainConfig field names of the --config.* options among the words (tyro spells a field
    with '-' or '_'; a flag's negation is --config.a.no-b)."""
    names = set(config_values(TrainConfig())) - {"steps"}
    given: list[str] = []
    for word in argv:
        if not word.startswith("--config."):
            continue
        name = word[len("--config."):].split("=", 1)[0].replace("-", "_")
        if name not in names:
            head, _, last = name.rpartition(".")
            name = f"{head}.{last[3:]}".lstrip(".") if last.startswith("no_") else name
        if name in names and name not in given:
            given.append(name)
    return tuple(given)


def train(args: TrainArgs) -> int:
    """Run `geoavatar train` for parsed arguments; 0 when the run finished, 130 when interrupted."""
    options = replace(args.run)  # the trainer fills in a resumed run's own values
    _check_options(args, options)
    values = config_values(args.config)
    overrides = {name: values[name] for name in args.overrides}
    resume = args.resume or args.extend is not None
    if resume:
        config, record, plan = _requested_on_resume(args, options, overrides), None, None
    else:
        config, record, plan = _new_run(args, options, overrides)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("once", ShortVideoWarning)
            result = run_training(options, config, resume=resume, extend=args.extend or 0, record=record)
    except ValueError as err:  # bad option values (device, resolution): one line, like a GeoAvatarError
        if isinstance(err, GeoAvatarError):
            raise
        raise OptionError(str(err)) from None
    last = result.last
    summary = f"{result.status} at step {result.step}/{result.steps} ({result.steps_per_second:.2f} steps/s)"
    if last is not None:
        summary += f": loss {last.losses['total']:.4f}, PSNR {last.psnr:.2f} dB, {last.num_gaussians} Gaussians"
    if plan is not None:
        summary += f"; {result.seconds / 60:.1f} of the {plan.minutes:g} minutes after the warm-up"
    print(f"{summary}\nrun: {result.run_dir}")
    if result.status != "finished":
        return 130
    if args.held_out_fit and not _fit_held_out(result.run_dir, options, args.held_out_frames):
        return 130
    if args.voice:
        _learn_voice(result.run_dir, options)
    return 0


def _fit_held_out(run_dir, options: RunOptions, frames: int) -> bool:
    """The held-out frames (at most `frames` of them, 0: all) fitted against the finished avatar
    (train/held_out_fit.py; silent without test frames); False on Ctrl-C (the avatar is saved; the fit writes nothing
    until it is complete)."""
    from geoavatar.train.held_out_fit import HeldOutFitConfig, fit_held_out, is_fitted

    config = HeldOutFitConfig(max_frames=frames or None)
    if is_fitted(run_dir, config):  # a --resume of a finished run: the fit is deterministic, so it would repeat itself
        print(f"held-out fit: already done for this checkpoint with these settings ({run_dir}/held_out.json)")
        return True
    try:
        fit_held_out(run_dir, config, progress=options.progress)
    except KeyboardInterrupt:
        print(f"held-out fit: interrupted; the avatar is saved, and its held-out frames keep the tracker's parameters "
              f"until `geoavatar train --out {run_dir} --resume` fits them")
        return False
    return True


def _learn_voice(run_dir, options: RunOptions) -> None:
    """The voice model of a finished run whose dataset has speech; one line either way."""
    from geoavatar.apps.voice import learn_voice
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.train.checkpoint import open_run

    if _voice_is_newer(run_dir):  # a --resume of a finished run: keep the voice it has (maybe `voice --steps`'s)
        print(f"voice: already learned after this avatar ({run_dir}/voice/); `geoavatar voice {run_dir}` learns it "
              "again")
        return
    run = open_run(run_dir, "cpu", options.flame_dir)
    sound = read_dataset_sound(run.info.data_root)
    if sound is None or not sound.activity.has_speech:
        print("voice: the dataset has no speech, so the avatar has no voice; prepare a video in which you talk to "
              "give it one")
        return
    learn_voice(run)


def _voice_is_newer(run_dir) -> bool:
    """Whether the run holds a readable voice model written after its final checkpoint."""
    from geoavatar.train.checkpoint import CHECKPOINT_DIR, FINAL_CHECKPOINT
    from geoavatar.voice import VoiceModel
    from geoavatar.voice.model import INFO_FILE, VOICE_DIR

    final, voice = Path(run_dir) / CHECKPOINT_DIR / FINAL_CHECKPOINT, Path(run_dir) / VOICE_DIR / INFO_FILE
    if not (final.is_file() and voice.is_file()) or voice.stat().st_mtime < final.stat().st_mtime:
        return False
    return VoiceModel.readable(run_dir)


train.parse_argv = parse_args  # geoavatar.cli parses the words with it (not from train's signature)


def default_schedule(schedule: str, options: RunOptions) -> tuple[int, str]:
    """The steps of a new run given no --steps / --minutes, and how they were chosen (printed, recorded in
    config.json). On CPU, --schedule auto also sets --resolution to CPU_RESOLUTION unless it was given
    (images are never upscaled)."""
    from geoavatar.runtime import resolve_device

    try:
        device = resolve_device(options.device).type
    except ValueError as err:
        raise OptionError(str(err)) from None
    if schedule == "paper" or device == "cuda":
        return PAPER_STEPS, f"--schedule {schedule} on {device}: the paper's {PAPER_STEPS} steps"
    if options.resolution is None:
        options.resolution = CPU_RESOLUTION
    return CPU_STEPS, (f"--schedule auto on cpu: {CPU_STEPS} steps at {options.resolution} px "
                       f"(the paper's {PAPER_STEPS}-step schedule at full size: --schedule paper)")


def _check_options(args: TrainArgs, options: RunOptions) -> None:
    """One-line errors naming the option, before anything is opened."""
    for name, value in (("--steps", args.steps), ("--extend", args.extend), ("--minutes", args.minutes),
                        ("--val-every", options.val_every), ("--ckpt-every", options.ckpt_every),
                        ("--log-every", options.log_every)):
        if value is not None and not value > 0:
            raise OptionError(f"{name} must be positive, got {value}")
    if args.held_out_frames < 0:
        raise OptionError(f"--held-out-frames must be 0 (all of them) or positive, got {args.held_out_frames}")
    if args.minutes is not None and args.steps is not None:
        raise OptionError("--minutes and --steps together: give one (--minutes chooses the steps)")
    if args.schedule is not None:
        given = [o for o, v in (("--steps", args.steps), ("--minutes", args.minutes), ("--extend", args.extend))
                 if v is not None] + (["--resume"] if args.resume else [])
        if given:
            raise OptionError(f"--schedule chooses the budget of a new run given no --steps or --minutes; "
                              f"drop it or {', '.join(given)}")
    if args.extend is not None:
        given = [o for o, v in (("--steps", args.steps), ("--minutes", args.minutes), ("--preset", options.preset))
                 if v is not None] + [f"--config.{n.replace('_', '-')}" for n in args.overrides]
        if given:
            raise OptionError(f"--extend continues the run's own configuration; drop {', '.join(given)}")
    elif args.minutes is not None and args.resume:
        raise OptionError("--minutes chooses the steps of a new run; --resume continues the run's own schedule "
                          "(to train a finished run longer: --extend N)")
    if options.data is None and not (args.resume or args.extend is not None):
        raise OptionError("--data is required for a new run (only --resume finds the run's own)")


def _new_run(args: TrainArgs, options: RunOptions, overrides: dict) -> tuple[TrainConfig, dict, BudgetPlan | None]:
    """A new run's configuration, what config.json records of it and the --minutes plan (None without): the
    --preset with the --config.* overrides on the paper's schedule, scaled to the steps that --minutes, --steps or
    --schedule choose (the milestones set by an override stay put). Sets `options.preset`, and with --schedule auto
    on a CPU `options.resolution` (default_schedule)."""
    options.preset = options.preset or DEFAULT_PRESET
    keep = [name for name in overrides if name in STEP_FIELDS]
    try:
        base = with_values(make_preset(options.preset), overrides)
    except ValueError as err:
        raise OptionError(f"--config: {err}") from None
    plan = None
    if args.minutes is not None:
        from geoavatar.train.budget import plan_budget

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ShortVideoWarning)  # the run itself warns
            plan = plan_budget(options, base, args.minutes, keep)
        print(plan.summary(), flush=True)
        steps, chosen_by = plan.steps, "--minutes"
    elif args.steps is not None:
        steps, chosen_by = args.steps, "--steps"
    else:
        steps, chosen_by = default_schedule(args.schedule or "auto", options)
        print(f"budget: {chosen_by}", flush=True)
    config = base.scaled_to(steps, keep)
    try:
        config.validate()
    except ValueError as err:
        raise OptionError(f"--config: {err}") from None
    record = {"overrides": overrides, "schedule": {
        "steps": steps, "chosen_by": chosen_by, "scaled_from": PAPER_STEPS, "not_scaled": keep,
        "budget": plan.to_json() if plan is not None else None}}
    return config, record, plan


def _requested_on_resume(args: TrainArgs, options: RunOptions, overrides: dict) -> TrainConfig | None:
    """The configuration --preset/--steps/--config.* ask for on --resume (None when none of them is given, or with
    --extend, which continues the run's own); the trainer refuses it (naming the differences) unless it is the run's
    own."""
    from geoavatar.train.checkpoint import config_from_json, load_checkpoint, run_checkpoint_path

    steps = args.steps
    if args.extend is not None or (steps is None and options.preset is None and not overrides):
        return None
    saved = config_from_json(load_checkpoint(run_checkpoint_path(options.out, "last"))["config"])
    if options.preset is not None:
        requested = make_preset(options.preset, steps or saved.steps)
    else:
        requested = saved.scaled_to(steps) if steps is not None else saved
    try:
        return with_values(requested, overrides)
    except ValueError as err:
        raise OptionError(f"--config: {err}") from None


__all__ = ["CommandLineConfig", "TrainArgs", "config_options_given", "default_schedule", "parse_args", "train"]
