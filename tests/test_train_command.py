"""`geoavatar train` as a command: the whole TrainConfig on the command line (defaults from --preset,
overrides recorded, set milestones not scaled), --extend (a run trained longer equals a run planned that
long), --minutes (a time budget picks the steps; the warm-up changes nothing else).

Runs use test_trainer's tiny subject (48 px, 12 frames) and 4-step schedule.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import warnings

import pytest
import tyro

from geoavatar import cli
from geoavatar.apps import train as train_app
from geoavatar.config import STEP_FIELDS, TrainConfig, config_values, preset
from geoavatar.data.splits import ShortVideoWarning
from geoavatar.train import budget
from geoavatar.train import checkpoint as ckpt
from geoavatar.config import config_values as _flat
from geoavatar.train.trainer import train
from test_trainer import STEPS, TOLERANCE, assert_same, learned_tensors, options, small_config, straight_run, subject  # noqa: F401

QUIET = ["--no-progress", "--val-every", "1000", "--ckpt-every", "1000", "--seed", "3"]
# small_config() on the command line: preset E, opacity 0.5 at the start, faster colours, no opacity reset,
# densification to the last step
SMALL = ["--config.model.init-opacity", "0.5", "--config.lr.features", "0.05", "--config.lr.opacity", "0.1",
         "--config.densify.reset-opacity-every", str(10 * STEPS), "--config.densify.stop", str(STEPS)]


def geoavatar_train(capsys, *words) -> tuple[int, str, str]:
    code = cli.main(["train", *map(str, words)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# --- parsing ----------------------------------------------------------------------------------


def test_readme_forms_parse_and_config_defaults_follow_the_preset(tmp_path):
    args = train_app.parse_args(["--data", "D", "--out", "R", "--steps", "3000", "--resolution", "256"])
    assert (str(args.run.data), str(args.run.out), args.steps, args.run.resolution) == ("D", "R", 3000, 256)
    assert args.run.preset is None and args.overrides == () and config_values(args.config)["model.face_sets"] == "aps"
    args = train_app.parse_args(["--out", "R", "--preset", "A", "--config.loss.lambda-angle", "0.5",
                                 "--config.aps_step=10", "--config.loss.no-use-angle", "--config.model.mouth",
                                 "geoavatar"])
    values = config_values(args.config)
    assert args.run.preset == "A" and values["model.face_sets"] == "gaussianavatars"  # A's default
    assert (values["loss.lambda_angle"], values["aps_step"], values["loss.use_angle"]) == (0.5, 10, False)
    assert args.overrides == ("loss.lambda_angle", "aps_step", "loss.use_angle", "model.mouth")


def test_help_lists_every_config_field_with_the_presets_defaults(capsys):
    with pytest.raises(SystemExit) as exit_info:
        train_app.parse_args(["--preset", "A", "--help"])
    assert exit_info.value.code == 0
    text = re.sub(r"[│\s]+", " ", capsys.readouterr().out)
    for name in set(config_values(TrainConfig())) - {"steps"}:
        assert f"--config.{name.replace('_', '-')}" in text, name
    assert "--config.steps" not in text  # --steps / --minutes set it
    for option in ("--data", "--out", "--preset", "--steps", "--minutes", "--extend", "--resume", "--resolution"):
        assert f"{option} " in text
    face_sets = text[text.index("--config.model.face-sets"):]
    assert "(default: gaussianavatars)" in face_sets[:300]  # preset A's, not E's


def test_bad_combinations_are_one_line_errors(tmp_path, capsys):
    for words, pattern in [
        (["--data", tmp_path, "--out", tmp_path / "r", "--minutes", "5", "--steps", "10"], "--minutes and --steps"),
        (["--out", tmp_path / "r", "--extend", "5", "--steps", "10"], "--extend continues the run's own.*--steps"),
        (["--out", tmp_path / "r", "--extend", "5", "--config.loss.tau-rigid", "1"], "drop --config.loss.tau-rigid"),
        (["--out", tmp_path / "r", "--resume", "--minutes", "5"], "--minutes chooses the steps of a new run"),
        (["--out", tmp_path / "r", "--extend", "0"], "--extend must be positive"),
        (["--data", tmp_path, "--out", tmp_path / "r", "--minutes", "0"], "--minutes must be positive"),
        (["--data", tmp_path, "--out", tmp_path / "r", "--steps", "10", "--config.aps-step", "11"],
         "aps_step must lie in \\[0, steps=10\\] \\(got 11\\)"),
        (["--out", tmp_path / "r", "--extend", "3"], "--extend continues a run, but there is none here"),
        (["--data", tmp_path, "--out", tmp_path / "r", "--config.mesh-prior.lambda-behind", "0.1"],
         "--config.mesh-prior.lambda-behind was removed: measured and rejected"),
        (["--data", tmp_path, "--out", tmp_path / "r", "--config.warped-view.no-colours-only"],
         "--config.warped-view.no-colours-only was removed"),
        (["--data", tmp_path, "--out", tmp_path / "r", "--schedule", "paper", "--steps", "10"],
         "--schedule chooses the budget of a new run.*--steps"),
        (["--out", tmp_path / "r", "--resume", "--schedule", "auto"], "--schedule chooses.*--resume"),
    ]:
        code, _, err = geoavatar_train(capsys, *words, "--no-progress")
        assert code == 2 and err.count("\n") == 1 and re.search(pattern, err), (words, err)
    assert not (tmp_path / "r" / "checkpoints").exists()


# --- a new run with overrides -----------------------------------------------------------------


def test_overrides_reach_the_run_and_config_json_records_everything(subject, tmp_path, capsys):  # noqa: F811
    out = tmp_path / "run"
    code, stdout, _ = geoavatar_train(capsys, "--data", subject, "--out", out, "--steps", STEPS, *QUIET, *SMALL,
                                      "--config.aps-step", "1", "--config.loss.lambda-angle", "0.05")
    assert code == 0 and "finished at step 4/4" in stdout
    record = json.loads((out / "config.json").read_text())
    saved = ckpt.load_run(out).config
    expected = train_app.with_values(small_config(), {"aps_step": 1, "loss.lambda_angle": 0.05})
    assert saved == expected  # aps_step 1 as given (scaled it would be 2); every other milestone scaled
    assert config_values(saved)["densify.every"] == 1 and saved.lr.position_decay_steps == 3 * STEPS
    assert set(config_values(TrainConfig())) == {k for k in _flat(record["config"])}  # every field recorded
    assert _flat(record["config"]) == json.loads(json.dumps(config_values(saved)))  # as JSON holds them (no tuples)
    assert record["preset"] == "E"
    assert record["overrides"] == {"model.init_opacity": 0.5, "lr.features": 0.05, "lr.opacity": 0.1,
                                   "densify.reset_opacity_every": 40, "densify.stop": STEPS, "aps_step": 1,
                                   "loss.lambda_angle": 0.05}
    schedule = record["schedule"]
    assert schedule["steps"] == STEPS and schedule["chosen_by"] == "--steps" and schedule["scaled_from"] == 200_000
    assert schedule["not_scaled"] == ["densify.reset_opacity_every", "densify.stop", "aps_step"]
    assert schedule["budget"] is None
    assert "overrides: model.init_opacity=0.5" in (out / "train.log").read_text()
    assert set(schedule["not_scaled"]) <= set(STEP_FIELDS)


# --- --extend ---------------------------------------------------------------------------------


def test_extend_equals_a_run_planned_that_long_and_an_interrupted_extension_resumes(subject, straight_run, tmp_path,  # noqa: F811
                                                                                    capsys):
    longer = small_config().extended(2)  # 6 steps, milestones of the 4-step run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        planned = train(options(subject, tmp_path / "planned"), longer)
    assert planned.status == "finished" and planned.step == STEPS + 2

    # a finished run extended twice on the command line (no --data: the run's own)
    twice = tmp_path / "twice"
    shutil.copytree(straight_run, twice)
    for extra, end in ((1, 5), (1, 6)):
        code, stdout, _ = geoavatar_train(capsys, "--out", twice, "--extend", extra, "--no-progress")
        assert code == 0 and f"finished at step {end}/{end}" in stdout
    assert_same(learned_tensors(tmp_path / "planned"), learned_tensors(twice), tolerance=TOLERANCE)
    record = json.loads((twice / "config.json").read_text())
    assert record["config"]["steps"] == 6 and record["config"]["densify"]["stop"] == STEPS
    assert record["extensions"] == [{"at_step": 4, "from_steps": 4, "to_steps": 5},
                                    {"at_step": 5, "from_steps": 5, "to_steps": 6}]
    log = (twice / "train.log").read_text()
    assert "extend: 4 -> 5 steps" in log and not re.search(r"step [56]: densify", log)
    assert ckpt.load_checkpoint(ckpt.run_checkpoint_path(twice, "final"))["step"] == 6

    # an extension stopped by Ctrl-C continues exactly with plain --resume
    stopped = tmp_path / "stopped"
    shutil.copytree(straight_run, stopped)

    def ctrl_c_at_5(step, state, report):
        if step == 5:
            os.kill(os.getpid(), signal.SIGINT)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        first = train(options(subject, stopped), None, resume=True, extend=2, callback=ctrl_c_at_5)
        assert first.status == "interrupted" and first.step == 5
        final = train(options(subject, stopped), None, resume=True)
    assert final.status == "finished" and final.step == 6
    assert_same(learned_tensors(tmp_path / "planned"), learned_tensors(stopped), tolerance=TOLERANCE)


# --- --minutes --------------------------------------------------------------------------------


class FakeClock:
    """Half a second per reading: every timed step, validation and checkpoint 'takes' 0.5 s."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        self.now += 0.5
        return self.now


def test_minutes_picks_the_steps_and_the_run_equals_that_many_steps(subject, tmp_path, capsys, monkeypatch):  # noqa: F811
    monkeypatch.setattr(budget, "clock", FakeClock())
    timed = tmp_path / "timed"
    code, stdout, _ = geoavatar_train(capsys, "--data", subject, "--out", timed, "--minutes", "0.21", *QUIET, *SMALL)
    assert code == 0, stdout
    record = json.loads((timed / "config.json").read_text())
    plan = record["schedule"]["budget"]
    steps = record["config"]["steps"]
    assert record["schedule"]["chosen_by"] == "--minutes" and plan["steps"] == steps == record["schedule"]["steps"]
    assert f"{steps} steps, estimated end" in stdout and plan["estimated_end"] in stdout
    # the fake clock: 0.5 s per step at either count, per validation image and per checkpoint
    assert plan["seconds_per_step"] == plan["seconds_per_step_grown"] == plan["mean_seconds_per_step"] == 0.5
    left = 0.21 * 60 - plan["warmup_seconds"] - plan["open_seconds"] - plan["overhead_seconds"]
    assert steps == int(left // 0.5) and 1 <= steps <= 6
    assert plan["overhead_seconds"] == 0.5 * 1 + 0.5 * 2  # one validation image, last + final checkpoints

    # the warm-up changed nothing but the step count
    straight = tmp_path / "straight"
    code, _, _ = geoavatar_train(capsys, "--data", subject, "--out", straight, "--steps", steps, *QUIET, *SMALL)
    assert code == 0
    assert_same(learned_tensors(straight), learned_tensors(timed), tolerance=TOLERANCE)

    code, _, err = geoavatar_train(capsys, "--data", subject, "--out", tmp_path / "short", "--minutes", "0.1", *QUIET)
    assert code == 2 and "--minutes 0.1 is too short: the warm-up took" in err
    assert not (tmp_path / "short" / "checkpoints").exists()


def test_a_new_run_without_a_budget_gets_one_that_finishes():
    """No --steps / --minutes: on CPU the short measured budget at 256 px (a size given stays), the paper's
    schedule with --schedule paper; the choice is a sentence for the terminal and config.json."""
    from geoavatar.config import CPU_RESOLUTION, CPU_STEPS, PAPER_STEPS
    from geoavatar.train.options import RunOptions

    cpu = RunOptions(out="r", device="cpu")
    steps, chosen_by = train_app.default_schedule("auto", cpu)
    assert (steps, cpu.resolution) == (CPU_STEPS, CPU_RESOLUTION) and "--schedule paper" in chosen_by
    small = RunOptions(out="r", device="cpu", resolution=128)
    assert train_app.default_schedule("auto", small)[0] == CPU_STEPS and small.resolution == 128
    full = RunOptions(out="r", device="cpu")
    assert train_app.default_schedule("paper", full)[0] == PAPER_STEPS and full.resolution is None


def test_the_chosen_budget_is_printed_and_recorded(subject, tmp_path, capsys, monkeypatch):  # noqa: F811
    monkeypatch.setattr(train_app, "CPU_STEPS", 2)  # the default's path, at a test's length
    code, out, _ = geoavatar_train(capsys, "--data", subject, "--out", tmp_path / "r", "--device", "cpu", *QUIET)
    assert code == 0 and "budget: --schedule auto on cpu: 2 steps at 256 px" in out
    record = json.loads((tmp_path / "r" / "config.json").read_text())
    assert record["schedule"]["steps"] == 2 and record["schedule"]["chosen_by"].startswith("--schedule auto on cpu")


def test_budget_model_accounts_for_the_growing_gaussian_count():
    base = preset("E")
    # linear in the count through the two measurements (1x and GROWN x)
    assert budget.step_time(1.0, 1.0, 4.0) == 1.0 and budget.step_time(budget.GROWN, 1.0, 4.0) == 4.0
    # E: 1x for the first 5 %, growing to GROWTH x until a third of the run (densify.stop, 33.5 %), then GROWTH x:
    # mean = 0.05 t(1) + 0.285 t((1 + G) / 2) + 0.665 t(G)
    growth = budget.GROWTH
    expected = (0.05 * 1.0 + 0.285 * budget.step_time((1 + growth) / 2, 1.0, 4.0)
                + 0.665 * budget.step_time(growth, 1.0, 4.0))
    assert budget.mean_step_seconds(base.scaled_to(1000), 1.0, 4.0) == pytest.approx(expected)
    assert budget.mean_step_seconds(base.scaled_to(1000), 1.0, 1.0) == pytest.approx(1.0)  # no slow-down measured
    no_densify = train_app.with_values(base, {"densify.stop": 0})
    assert budget.mean_step_seconds(no_densify.scaled_to(1000, ("densify.stop",)), 1.0, 4.0) == 1.0
    # more time, more steps; the slow-down costs steps; every count fits the time it was chosen for
    fast, _, _ = budget.steps_for_budget(600, base, (), 0.1, 0.1, 1.0, 1.0)
    slow, mean, overhead = budget.steps_for_budget(600, base, (), 0.1, 0.3, 1.0, 1.0)
    more, _, _ = budget.steps_for_budget(1200, base, (), 0.1, 0.3, 1.0, 1.0)
    assert slow < fast and more > 2 * slow - 50
    assert slow * mean + overhead <= 600
    mean_next = budget.mean_step_seconds(base.scaled_to(slow + 1), 0.1, 0.3)
    assert (slow + 1) * mean_next + budget.overhead_seconds(slow + 1, None, None, 1.0, 1.0) > 600
    assert budget.steps_for_budget(1.0, base, (), 0.1, 0.3, 1.0, 1.0)[0] == 0


def test_cli_table_runs_train_through_its_own_parser():
    assert cli._resolve(cli.COMMANDS["train"]).parse_argv is train_app.parse_args
    with pytest.raises(SystemExit):
        tyro.cli(train_app.TrainArgs, args=["--out", "R", "--config.steps", "5"])  # steps: --steps / --minutes only
