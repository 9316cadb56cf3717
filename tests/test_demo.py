"""`geoavatar demo` end to end on a tiny budget: every stage of a user's path runs (train, fit the test frames
against the avatar, eval, learn the voice, score it, speak), the report leads with the fitted test frames' score,
the pictures are larger than the training images, and the report points at real files."""

import functools
import json
import re
import shlex

import numpy as np
import pytest
from PIL import Image

from geoavatar import cli
from geoavatar.apps.demo import demo

# 128 px generated images, trained at 32 px: the pictures (128 px) are larger than the training images; 60 frames hold
# 2.1 s of the subject's voice, enough to learn one (8 frames would not: the speech stages would be skipped)
PICTURES = 128
TINY = dict(steps=4, frames=60, size=PICTURES, resolution=32, picture_resolution=PICTURES,
            driver_frames=3, voice_steps=20, device="cpu", backend="torch")
TEST_FRAMES = 15


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    assert demo(out=out, **TINY) == 0
    return out


def _summary(path):
    return json.loads(path.read_text())["summary"]


def test_demo_writes_report_with_metrics_videos_and_stills(demo_out, capsys):
    out = demo_out
    report = (out / "report.md").read_text()
    assert "PSNR" in report and "| **total** |" in report and "backend 'torch'" in report
    for name in ("render_test.mp4", "orbit.mp4", "reenact.mp4", "speak.mp4", "render.png", "orbit.png", "reenact.png",
                 "speak.png"):
        assert (out / name).stat().st_size > 0, name
    # every picture the report links exists
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report):
        assert (out / link).is_file(), link
    assert (out / "run" / "eval" / "test" / "metrics.json").is_file()
    assert {"index.html", "player.js", "avatar.json", "avatar.bin", "clip.bin"} <= {f.name for f in (out / "web").iterdir()}

    # a second call finds every stage complete, rewrites the report and keeps the measured times
    capsys.readouterr()
    assert demo(out=out, **TINY) == 0
    assert f"--directory {out / 'web'}" in capsys.readouterr().out  # how to open the web player
    assert (out / "report.md").read_text() == report


def test_demo_fits_only_the_test_frames_against_its_avatar(demo_out):
    import torch

    from geoavatar.train.checkpoint import load_run

    fit = json.loads((demo_out / "run" / "held_out.json").read_text())
    run = load_run(demo_out / "run", torch.device("cpu"))
    test = sorted(json.loads((demo_out / "data" / "subject0" / "transforms_test.json").read_text())["frames"],
                  key=lambda f: f["timestep_index"])
    assert fit["frames"] == TEST_FRAMES and fit["checkpoint_step"] == TINY["steps"]
    assert sorted(run.info.held_out) == [f["timestep_index"] for f in test]  # the held-out frames, and only they
    settings = json.loads((demo_out / "run" / "eval" / "test" / "metrics.json").read_text())["settings"]
    assert settings["test_params"].startswith("fitted against this avatar")
    written = json.loads((demo_out / "run" / "eval" / "test@dataset_params" / "metrics.json").read_text())["settings"]
    assert written["test_params"] == "as the dataset holds them (no prepare or track report beside it)"


def test_demo_report_leads_with_the_fitted_score(demo_out):
    out = demo_out
    report = (out / "report.md").read_text()
    tracked = _summary(out / "run" / "eval" / "test" / "metrics.json")
    written = _summary(out / "run" / "eval" / "test@dataset_params" / "metrics.json")

    # the first figure of the report is the fitted test frames' PSNR, with its SSIM and LPIPS
    first = re.search(r"\*\*PSNR ([\d.]+) dB · SSIM ([\d.]+) · LPIPS ([\d.]+)\*\*", report)
    assert first and re.search(r"[\d.]+ dB", report).group(0) == f"{first.group(1)} dB"
    assert float(first.group(1)) == pytest.approx(tracked["psnr"]["mean"], abs=0.006)
    assert float(first.group(2)) == pytest.approx(tracked["ssim"]["mean"], abs=6e-4)
    assert float(first.group(3)) == pytest.approx(tracked["lpips"]["mean"], abs=6e-4)
    assert report.index(first.group(0)) < report.index("## Pictures")
    # the written parameters' score beside it, in the row below the fitted one, with its one-line explanation
    lines = report.splitlines()
    rows = [i for i, line in enumerate(lines) if line.startswith(("| **fitted against the avatar**", "| written "))]
    assert len(rows) == 2 and rows[1] == rows[0] + 1
    rows = [lines[i] for i in rows]
    assert f"**{tracked['psnr']['mean']:.2f}** ± {tracked['psnr']['std']:.2f}" in rows[0]
    assert f"{written['psnr']['mean']:.2f} ± {written['psnr']['std']:.2f}" in rows[1]
    assert f"{written['lpips']['mean']:.3f}" in rows[1]
    assert "simulated tracker error" in report

    summary = json.loads((out / "report.json").read_text())
    assert summary["test"]["lead"] == "fitted"
    assert summary["test"]["fitted"]["psnr"]["mean"] == pytest.approx(tracked["psnr"]["mean"])
    assert summary["test"]["written"]["psnr"]["mean"] == pytest.approx(written["psnr"]["mean"])
    assert summary["frames_evaluated"] == TEST_FRAMES and summary["held_out_fit"]["frames"] == TEST_FRAMES
    assert summary["pictures"]["resolution"] == PICTURES
    assert set(summary["seconds"]) >= {"fit the test frames against the avatar", "evaluate (test split)"}


def test_demo_speaks_a_clip_with_its_sound_and_reports_its_voice(demo_out):
    import av

    with av.open(str(demo_out / "speak.mp4")) as container:
        assert [stream.type for stream in container.streams] == ["video", "audio"]
    speech = json.loads((demo_out / "run" / "eval" / "speech" / "metrics.json").read_text())
    assert set(speech["baselines"]) == {"mean_face", "nearest", "linear"}
    report = (demo_out / "report.md").read_text()
    assert "## The avatar speaks" in report and f"mouth-open r {speech['mouth_open_correlation']:.2f}" in report
    summary = json.loads((demo_out / "report.json").read_text())
    assert summary["speech"]["lip_vertex_error"] == pytest.approx(speech["lip_vertex_error"])
    assert "learn the voice" in summary["seconds"]


def test_demo_stills_are_larger_than_the_training_images(demo_out):
    assert json.loads((demo_out / "run" / "config.json").read_text())["run"]["resolution"] == 32
    for name in ("render", "orbit", "reenact"):
        with Image.open(demo_out / f"{name}.png") as image:
            assert image.height >= PICTURES, (name, image.size)
    with Image.open(demo_out / "render.png") as image:  # ground truth | render | error, 128 px each
        assert image.size == (3 * PICTURES, PICTURES)
        assert np.asarray(image).std() > 0


def test_demo_report_commands_parse_with_the_cli(demo_out, monkeypatch):
    """The report's step-by-step commands (a user's path) are real command lines of the CLI."""
    block = (demo_out / "report.md").read_text().split("or the same steps one by one")[1]
    lines = [re.sub(r"\s+#.*$", "", line) for line in re.search(r"```bash\n(.*?)```", block, re.S).group(1).splitlines()]
    calls = []
    resolve = cli._resolve

    def recorder(target):
        func = resolve(target)

        @functools.wraps(func)
        def record(*args, **kwargs):
            calls.append((target, kwargs))
            return 0

        return record

    monkeypatch.setattr(cli, "_resolve", recorder)
    for line in lines:
        assert cli.main(shlex.split(line)[1:]) == 0, line
    commands = [target.split(":")[1] for target, _ in calls]
    assert commands[:4] == ["synth", "train", "eval_runs", "eval_runs"] and "render" in commands
    assert calls[3][1]["test_params"] == "dataset"
