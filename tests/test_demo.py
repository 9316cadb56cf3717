"""`geoavatar demo` end to end on a tiny budget: every stage runs and the report points at real files."""

import re

from geoavatar.apps.demo import demo


def test_demo_writes_report_with_metrics_videos_and_stills(tmp_path, capsys):
    out = tmp_path / "demo"
    assert demo(out=out, steps=4, frames=8, size=48, resolution=48, driver_frames=3, device="cpu", backend="torch") == 0
    assert f"--directory {out / 'web'}" in capsys.readouterr().out  # how to open the web player
    report = (out / "report.md").read_text()
    assert "PSNR" in report and "| **total** |" in report and "backend 'torch'" in report
    for name in ("render_test.mp4", "orbit.mp4", "reenact.mp4", "render.png", "orbit.png", "reenact.png"):
        assert (out / name).stat().st_size > 0, name
    # every picture the report links exists
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report):
        assert (out / link).is_file(), link
    assert (out / "run" / "eval" / "test" / "metrics.json").is_file()
    assert {"index.html", "player.js", "avatar.json", "avatar.bin", "clip.bin"} <= {f.name for f in (out / "web").iterdir()}

    # a second call finds every stage complete, rewrites the report and keeps the measured times
    assert demo(out=out, steps=4, frames=8, size=48, resolution=48, driver_frames=3, device="cpu", backend="torch") == 0
    assert (out / "report.md").read_text() == report
