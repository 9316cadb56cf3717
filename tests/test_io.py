"""geoavatar.io: atomic files/folders with the umask's mode, one mp4 rule, and a full disk as one clear error."""

import errno
import os

import numpy as np
import pytest

from geoavatar.data.layout import LayoutWriter
from geoavatar.errors import DiskFullError
from geoavatar.io import atomic
from geoavatar.io.atomic import atomic_folder, atomic_write_json, atomic_write_png, atomic_write_text
from geoavatar.io.ply import GaussianPly, read_gaussian_ply, write_gaussian_ply
from geoavatar.io.video import Mp4Writer, write_mp4
from geoavatar.train import checkpoint as ckpt


@pytest.fixture
def umask_027():
    """Run under umask 027 (not the usual 022, so a hard-coded 0o644 would fail)."""
    previous = os.umask(0o027)
    atomic._umask.cache_clear()
    yield
    os.umask(previous)
    atomic._umask.cache_clear()


def _no_temporaries(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


def test_files_and_folders_get_the_umask_mode(tmp_path, umask_027):
    text = atomic_write_text(tmp_path / "report.md", "# hi\n")
    png = atomic_write_png(tmp_path / "still.png", np.zeros((4, 6, 3), np.uint8))
    with atomic_folder(tmp_path / "seq") as folder:
        atomic_write_json(folder / "a.json", {"x": 1})
    for path in (text, png, tmp_path / "seq" / "a.json"):
        assert path.stat().st_mode & 0o777 == 0o640, path
    assert (tmp_path / "seq").stat().st_mode & 0o777 == 0o750
    assert _no_temporaries(tmp_path) == []


def test_an_error_leaves_the_old_file_and_folder(tmp_path):
    atomic_write_text(tmp_path / "a.txt", "old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic.atomic_file(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "old.txt").write_text("old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_folder(tmp_path / "seq") as folder:
            (folder / "new.txt").write_text("new")
            raise RuntimeError("boom")
    assert (tmp_path / "a.txt").read_text() == "old"
    assert [p.name for p in (tmp_path / "seq").iterdir()] == ["old.txt"]
    with atomic_folder(tmp_path / "seq") as folder:  # replacing an existing folder
        (folder / "new.txt").write_text("new")
    assert [p.name for p in (tmp_path / "seq").iterdir()] == ["new.txt"]
    assert _no_temporaries(tmp_path) == []
    (tmp_path / "was_a_file").write_text("old")
    with atomic_folder(tmp_path / "was_a_file") as folder:  # replacing a file: nothing of it left behind
        (folder / "new.txt").write_text("new")
    assert (tmp_path / "was_a_file" / "new.txt").is_file() and _no_temporaries(tmp_path) == []


@pytest.fixture
def disk_full(monkeypatch):
    """Every fsync fails with ENOSPC, as it does when the data no longer fits (the write before it was buffered)."""

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)


def _one_line_disk_full(err, path):
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: ") and "disk is full" in message
    assert err.value.errno == errno.ENOSPC
    return message


def test_checkpoint_on_a_full_disk_names_the_last_good_one(tmp_path, monkeypatch):
    last = tmp_path / "checkpoints" / "last.pt"
    ckpt.save_checkpoint(last, {"step": 10})
    good = last.read_bytes()
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left")))
    with pytest.raises(DiskFullError) as err:
        ckpt.save_checkpoint(last, {"step": 20})
    message = _one_line_disk_full(err, last)
    assert f"last good checkpoint: {last} (step 10)" in message
    assert last.read_bytes() == good and _no_temporaries(last.parent) == []
    # final.pt failing: last.pt is the good one; a new run without any checkpoint says so
    with pytest.raises(DiskFullError, match=f"last good checkpoint: {last} \\(step 10\\)"):
        ckpt.save_checkpoint(last.with_name("final.pt"), {"step": 20})
    with pytest.raises(DiskFullError, match="last good checkpoint: none written yet"):
        ckpt.save_checkpoint(tmp_path / "other" / "checkpoints" / "last.pt", {"step": 1})
    monkeypatch.undo()
    assert ckpt.load_checkpoint(last)["step"] == 10


def test_ply_and_report_on_a_full_disk(tmp_path, disk_full):
    ply, report = tmp_path / "avatar.ply", tmp_path / "report.md"
    ply.write_bytes(b"old ply")
    report.write_text("old report")
    gaussians = GaussianPly(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2), np.zeros((2, 3)),
                            np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(DiskFullError) as err:
        write_gaussian_ply(ply, gaussians)
    assert "the previous avatar.ply is unchanged" in _one_line_disk_full(err, ply)
    with pytest.raises(DiskFullError) as err:
        atomic_write_text(report, "# new report\n")
    _one_line_disk_full(err, report)
    with pytest.raises(DiskFullError, match="nothing was written"):
        atomic_write_json(tmp_path / "timings.json", {})
    assert ply.read_bytes() == b"old ply" and report.read_text() == "old report"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["avatar.ply", "report.md"]


def test_mp4_on_a_full_disk(tmp_path, disk_full):
    out = tmp_path / "render.mp4"
    out.write_bytes(b"old video")
    with pytest.raises(DiskFullError) as err:
        with Mp4Writer(out) as video:
            video.write(np.zeros((8, 8, 3), np.uint8))
    _one_line_disk_full(err, out)
    assert out.read_bytes() == b"old video" and _no_temporaries(tmp_path) == []


def test_dataset_on_a_full_disk(tmp_path, monkeypatch):
    root = tmp_path / "data"
    root.mkdir()
    (root / "keep.txt").write_text("the old dataset")
    writer = LayoutWriter(root, head_model="openhead", image_size=(8, 8), shape=np.zeros(4), overwrite=True)
    params = {k: np.zeros(n) for k, n in {"expr": 4, "rotation": 3, "neck_pose": 3, "jaw_pose": 3, "eyes_pose": 6,
                                           "translation": 3}.items()}
    viewmat, K = np.eye(4), np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]])
    writer.add_frame(0, np.zeros((8, 8, 3), np.uint8), params, viewmat, K)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez", full)  # the next frame's parameter file does not fit
    with pytest.raises(DiskFullError) as err:
        writer.add_frame(1, np.zeros((8, 8, 3), np.uint8), params, viewmat, K)
    assert f"{root} is unchanged" in _one_line_disk_full(err, root)
    assert [p.name for p in root.iterdir()] == ["keep.txt"] and _no_temporaries(tmp_path) == []


def test_one_odd_size_rule_pads_with_the_edge(tmp_path):
    frame = np.zeros((15, 21, 3), np.uint8)
    frame[-1] = 200  # the last row is repeated, not cropped away
    path = write_mp4(tmp_path / "odd.mp4", [frame] * 2, fps=10)
    import av

    with av.open(str(path)) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(decoded) == 2 and decoded[0].shape == (16, 22, 3)
    assert decoded[0][-1, 5, 0] > 150 and decoded[0][2, 5, 0] < 50
    assert path.stat().st_mode & 0o777 == atomic.file_mode()


def test_ply_round_trip_through_the_io_layer(tmp_path):
    g = GaussianPly(np.random.rand(3, 3), np.zeros((3, 3)), np.zeros(3), np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1)))
    back = read_gaussian_ply(write_gaussian_ply(tmp_path / "a.ply", g))
    np.testing.assert_allclose(back.means, g.means.astype(np.float32))
