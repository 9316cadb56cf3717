"""User errors (GeoAvatarError) become one line and exit status 2 at the CLI; bugs keep their traceback."""

import pickle

import pytest

from geoavatar import cli
from geoavatar.data import DatasetError
from geoavatar.errors import DiskFullError, GeoAvatarError, OptionError
from geoavatar.eval.lpips import LPIPSWeightsError
from geoavatar.head.flame import FlameFileError, FlameFileNotFoundError
from geoavatar.io.safe_pickle import ForbiddenPickleGlobal, UnreadablePickle
from geoavatar.prep.errors import PrepareError
from geoavatar.train.checkpoint import RunError
from geoavatar.train.trainer import TrainingDiverged
from head_fakes import procedural_head, write_fake_flame


@pytest.mark.parametrize("cls, old_base", [
    (RunError, ValueError), (DatasetError, ValueError), (PrepareError, RuntimeError),
    (TrainingDiverged, RuntimeError), (ForbiddenPickleGlobal, pickle.UnpicklingError),
    (UnreadablePickle, pickle.UnpicklingError), (FlameFileNotFoundError, FileNotFoundError),
    (FlameFileError, ValueError), (LPIPSWeightsError, FileNotFoundError), (OptionError, ValueError),
    (DiskFullError, OSError),
])
def test_user_errors_share_the_base_and_keep_their_old_one(cls, old_base):
    assert issubclass(cls, GeoAvatarError) and issubclass(cls, old_base)


def test_disk_full_error_prints_its_message_not_errno():
    err = DiskFullError("run/last.pt: the disk is full", 28, "run/last.pt")
    assert str(err) == "run/last.pt: the disk is full" and err.errno == 28 and err.filename == "run/last.pt"


class _RunsCode:
    def __reduce__(self):
        import os

        return (os.system, ("true",))


def _evil_flame(folder):
    write_fake_flame(folder, procedural_head(), "2023")
    (folder / "flame2023.pkl").write_bytes(pickle.dumps({"v_template": _RunsCode()}, protocol=2))
    return folder


def test_forbidden_flame_pickle_is_one_line_at_the_cli(tmp_path, capsys):
    folder = _evil_flame(tmp_path / "flame")
    code = cli.main(["head", "show", "--model", "flame", "--flame-dir", str(folder), "--out", str(tmp_path / "h.png")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("geoavatar head show: ") and "flame2023.pkl" in err and "refusing to load" in err
    assert not (tmp_path / "h.png").exists()


def test_missing_flame_folder_is_one_line_at_the_cli(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("GEOAVATAR_FLAME_DIR", raising=False)
    code = cli.main(["head", "show", "--model", "flame", "--flame-dir", str(tmp_path / "none"),
                     "--out", str(tmp_path / "h.png")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("geoavatar head show: ") and err.count("\n") == 1 and "none" in err


def test_a_bug_keeps_its_traceback(tmp_path, monkeypatch):
    import geoavatar.head

    def broken(*args, **kwargs):
        raise ValueError("an internal bug")  # a plain ValueError is not a user error any more

    monkeypatch.setattr(geoavatar.head, "load_head_model", broken)
    with pytest.raises(ValueError, match="an internal bug"):
        cli.main(["head", "show", "--out", str(tmp_path / "h.png")])


# --- bad input, one line each -------------------------------------------------------------------------------


def _one_line(capsys, argv: list[str]) -> str:
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_prepare_into_a_file_is_one_line_naming_out(tmp_path, capsys):
    video = tmp_path / "talk.mp4"
    video.write_bytes(b"")
    taken = tmp_path / "notes.txt"
    taken.write_text("mine")
    err = _one_line(capsys, ["prepare", str(video), "--out", str(taken)])
    assert err.startswith(f"geoavatar prepare: --out {taken}: is a file, not a folder"), err
    err = _one_line(capsys, ["prepare", str(video), "--out", str(taken / "talk")])  # a folder below a file
    assert err.startswith(f"geoavatar prepare: --out {taken / 'talk'}: {taken} is a file, not a folder"), err
    assert taken.read_text() == "mine"


def test_an_unknown_split_names_each_split_once(tmp_path, capsys):
    from apps_fixtures import make_subject, make_untrained_run

    run = make_untrained_run(make_subject(tmp_path / "data", frames=4), tmp_path / "run")
    err = _one_line(capsys, ["export", str(run), "--format", "web", "--split", "nosuch", "--out",
                             str(tmp_path / "player"), "--no-progress"])
    assert err == "geoavatar export: --split must be one of all, train, val, test; got 'nosuch'\n", err
    assert not (tmp_path / "player").exists()
