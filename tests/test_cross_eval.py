"""`geoavatar eval RUN --driver DATA [--transfer ...]` (#30): a cross re-enactment scored per mode and per frame with
renders without a face counted; plain `geoavatar eval RUN` adds the face scores to the test split's summary.

An untrained run (opacity 0.5) of a generated subject at 64 px, driven by another generated subject; the face
detector finds its face in these small renders, and one render is replaced by an empty picture, so that the counting
of renders without a face is tested too."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from apps_fixtures import make_subject, make_untrained_run
from geoavatar import cli
from geoavatar.animation.sources.driver import DrivenAvatar
from geoavatar.eval.cross import cross_dir

SIZE = 64


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("cross-eval")
    run = make_untrained_run(make_subject(root / "avatar", subject=0, frames=8, size=SIZE), root / "run",
                             init_opacity=0.5)
    driver = make_subject(root / "driver", subject=1, frames=6, size=SIZE, seed=3)
    return run, driver


def test_cross_eval_scores_each_mode_and_counts_faceless_renders(setup, capsys, monkeypatch):
    run, driver = setup
    render = DrivenAvatar.render

    def no_face_at_timestep_2(self, item, mode=None):
        rgb = render(self, item, mode)
        return torch.full_like(rgb, 0.5) if item["timestep"] == 2 else rgb

    monkeypatch.setattr(DrivenAvatar, "render", no_face_at_timestep_2)
    code = cli.main(["eval", str(run), "--driver", str(driver), "--transfer", "relative", "subspace", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    folder = cross_dir(run, driver.name)
    report = json.loads((folder / "metrics.json").read_text())
    assert set(report["summary"]) == {"relative", "subspace"} and report["driver"] == driver.name
    for mode, frames in report["frames"].items():
        summary = report["summary"][mode]
        assert [f["timestep"] for f in frames] == list(range(6))
        found = [f for f in frames if f["face_found"]]
        assert not frames[2]["face_found"] and len(found) >= 3  # the empty render, and real ones with a face
        assert summary["faces"]["frames"] == 6 and summary["faces"]["render_found"] == len(found)
        assert summary["faces"]["render_missing"] == 6 - len(found)
        assert all(f["id_similarity"] is None and f["expression_similarity"] is None for f in frames
                   if not f["face_found"])  # counted, never scored
        assert summary["id_similarity"]["count"] == sum(f["id_similarity"] is not None for f in frames)
        assert summary["faces"]["source_found"] == sum(f["source_face_found"] for f in frames) > 0
    markdown = (folder / "metrics.md").read_text()
    assert "| relative |" in markdown and "| subspace |" in markdown and "renders with a face" in markdown
    assert "not ArcFace" in markdown


def test_cross_eval_option_errors_are_one_line(setup, capsys):
    run, driver = setup
    for argv, message in [
        (["--driver", str(driver), "--relative", "--transfer", "statistics"], "--relative means --transfer relative"),
        (["--transfer", "subspace"], "go with --driver"),
        (["--driver", str(driver), "--driver-video", str(driver / "x.mp4")], "exactly one of --driver"),
        (["--driver", str(run / "missing")], "--driver"),
    ]:
        code = cli.main(["eval", str(run), "--no-progress", *argv])
        err = capsys.readouterr().err.strip()
        assert code == 2 and message in err and "Traceback" not in err, (argv, err)


def test_plain_eval_adds_the_face_scores_to_the_test_summary(setup, capsys):
    run, _ = setup
    assert cli.main(["eval", str(run), "--no-progress", "--no-floaters", "--no-mouth"]) == 0
    report = json.loads((run / "eval" / "test" / "metrics.json").read_text())
    frames = report["frames"]
    for name in ("id_similarity", "expression_similarity"):
        assert report["summary"][name]["count"] == sum(f[name] is not None for f in frames)
    assert report["faces"]["faces"]["frames"] == len(frames)
    assert report["settings"]["faces"]["reference_frames"] > 0
    assert "ID similarity (dlib)" in (run / "eval" / "test" / "metrics.md").read_text()
    assert cli.main(["eval", str(run), "--no-progress", "--no-floaters", "--no-mouth", "--no-faces"]) == 0
    report = json.loads((run / "eval" / "test" / "metrics.json").read_text())
    assert report["faces"] is None and report["summary"]["id_similarity"]["count"] == 0
