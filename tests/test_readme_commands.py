"""Every `geoavatar ...` command line of README.md parses with the real CLI, and the cheap ones run on tiny
data, so that the docs and the CLI cannot drift apart.

Command lines are the `geoavatar` lines of its ```bash blocks and the inline `geoavatar ... --option`
spans. A synopsis (`geoavatar train --data DIR --out RUN [--preset E] [--steps N]`) is checked twice:
with every optional part left out and with every one put in (`a|b` takes `a`). Placeholders map to
fixtures: RUN -> a 2-step run, DATA / DIR -> a 48 px generated subject, talk.mp4 -> a 6-frame clip cut
from a shared test video (without the shared folder: of a still photograph); N, R, F, E -> small numbers /
preset E. Running adds options that keep it cheap (CHEAP below: fewer frames, steps and pixels; the viewer
starts and stops), after the README's own, so the README's line itself is what gets parsed.
"""

from __future__ import annotations

import functools
import re
import shlex
import shutil
import warnings
from dataclasses import replace
from fractions import Fraction
from pathlib import Path

import pytest

from apps_fixtures import make_run, make_subject
from conftest import face_photo_video, shared_video
from geoavatar import cli
from geoavatar.apps import train as train_app
from geoavatar.config import CPU_STEPS
from geoavatar.data.splits import ShortVideoWarning

README = Path(__file__).resolve().parents[1] / "README.md"
MAKEFILE = README.parent / "Makefile"

# Options appended when a command runs here (later options win), so that a README line runs in seconds.
CHEAP: dict[str, list[str]] = {
    "synth": ["--frames", "8", "--size", "48", "--no-progress"],
    "train": ["--steps", "2", "--resolution", "32", "--no-progress"],
    "prepare": ["--size", "64", "--max-frames", "6", "--no-progress", "--no-overlay"],
    "eval": ["--max-frames", "1", "--lpips-net", "alex", "--no-progress", "--device", "cpu"],
    "render": ["--max-frames", "2", "--no-progress", "--device", "cpu"],
    "reenact": ["--max-frames", "2", "--no-progress", "--device", "cpu"],
    "orbit": ["--frames", "2", "--resolution", "32", "--no-progress", "--device", "cpu"],
    "export": ["--no-progress"],
    "view": ["--port", "0", "--no-serve-forever", "--device", "cpu"],
    "bench": ["--resolution", "32", "--iterations", "1", "--warmup", "0", "--no-progress", "--device", "cpu"],
    "head show": ["--size", "64"],
    "drive": ["--init-seconds", "0.12", "--iterations", "2", "--size", "32", "--no-status", "--device", "cpu"],
}
# Lines that are only parsed: the whole demo, tables over runs the README names but the test lacks, and
# (to keep this test near a minute on 2 shared cores) prepare, eval and head show, whose own tests run them; speak and
# voice need a run with a voice model (a dataset with speech): tests/test_speak.py and test_voice.py run them.
PARSE_ONLY = ("demo", "eval", "prepare", "head show", "ablate", "speak", "voice")
# Commands whose every README line runs; the others run their first line only (synth, train: the rest
# differ in sizes and lengths that CHEAP overrides anyway).
RUN_EVERY_LINE = ("render", "reenact", "orbit", "export", "view", "bench", "--help")
PLACEHOLDERS = {"N": "2", "R": "32", "F": "25", "E": "E"}


# --- reading the README ------------------------------------------------------------------------------


def _expand(line: str) -> list[str]:
    """A synopsis with [optional] parts -> (without them, with them; `a|b` -> `a`); else the line."""
    if "[" not in line:
        return [line]
    bare = re.sub(r"\s*\[[^\]]*\]", "", line)
    full = re.sub(r"\[([^\]]*)\]", lambda m: re.sub(r"(\S+?)\|\S+", r"\1", m.group(1)), line)
    return [bare, full]


def readme_commands(text: str) -> list[str]:
    """The `geoavatar` command lines of the README (comments stripped, synopses expanded), in order."""
    lines: list[str] = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for raw in block.splitlines():
            line = re.sub(r"\s+#.*$", "", raw).strip()
            if line.startswith("geoavatar"):
                lines.extend(_expand(line))
    outside = re.sub(r"```.*?```", "", text, flags=re.S)
    for span in re.findall(r"`(geoavatar [^`]*)`", outside):
        if " -" in span:  # a command line, not just a command's name
            lines.extend(_expand(span))
    return lines


def make_targets(text: str) -> list[str]:
    return re.findall(r"^make ([\w-]+)", "\n".join(re.findall(r"```bash\n(.*?)```", text, flags=re.S)), flags=re.M)


def with_numbers(argv: list[str]) -> list[str]:
    """A synopsis' value placeholders (--steps N, --preset E, ...) replaced by values."""
    return [PLACEHOLDERS.get(word, word) if i and argv[i - 1].startswith("--") else word for i, word in enumerate(argv)]


def command_of(argv: list[str]) -> str:
    table, words = cli.COMMANDS, []
    for word in argv:
        if word not in table:
            break
        words.append(word)
        if not isinstance(table[word], dict):
            break
        table = table[word]
    return " ".join(words)


TEXT = README.read_text()
COMMANDS = readme_commands(TEXT)


def test_the_readme_has_command_lines():
    # The parser must keep finding the lines, or every other check here would pass on nothing.
    assert len(COMMANDS) >= 15
    used = {command_of(shlex.split(line)[1:]) for line in COMMANDS}
    assert {"prepare", "train", "eval", "render", "reenact", "orbit", "export", "view", "bench", "synth"} <= used
    assert "geoavatar prepare talk.mp4 --out data/talk" in " ".join(COMMANDS)


def test_readme_make_targets_exist():
    targets = set(re.findall(r"^([\w-]+):", MAKEFILE.read_text(), flags=re.M))
    for target in make_targets(TEXT):
        assert target in targets, f"README: make {target}: no such target in the Makefile"


# --- parsing every line with the real CLI, nothing run -------------------------------------------------


@pytest.fixture
def recorded(monkeypatch):
    """cli.main parses with each command's real signature and records the arguments instead of running."""
    calls: list[tuple[str, dict]] = []
    resolve = cli._resolve

    def recorder(target: str):
        func = resolve(target)

        @functools.wraps(func)
        def record(*args, **kwargs):
            calls.append((target, kwargs if not args else {"_args": args, **kwargs}))
            return 0

        return record

    monkeypatch.setattr(cli, "_resolve", recorder)
    return calls


@pytest.mark.parametrize("line", COMMANDS)
def test_readme_line_parses(line, recorded, capsys):
    argv = with_numbers(shlex.split(line))
    assert argv[0] == "geoavatar"
    try:
        code = cli.main(argv[1:])
    except SystemExit as exit:  # tyro's exit on a parse error
        raise AssertionError(f"README line does not parse: {line}\n{capsys.readouterr().err[-2000:]}") from None
    assert code == 0, f"README line: {line}"
    if argv[1:] and argv[1] not in ("--help", "-h"):
        assert len(recorded) == 1, f"README line ran no command: {line}"


# The most a README `train` line may cost on a CPU, in steps at 256 px: twice the default budget (about
# 10 minutes for a 300-frame video on 2 cores), so that none starts a job a user would not wait for. The
# run test below shortens every train line; this checks the budget each line chooses as written.
MOST_STEPS_AT_256 = 2 * CPU_STEPS
MOST_MINUTES = 30


def test_readme_train_lines_choose_a_budget_a_user_waits_for():
    checked = 0
    for line in COMMANDS:
        argv = with_numbers(shlex.split(line))[1:]
        if command_of(argv) != "train" or {"--resume", "--extend", "--help"} & set(argv):
            continue
        args = train_app.parse_args(argv[1:])
        if args.minutes is not None:
            assert args.minutes <= MOST_MINUTES, f"README line trains {args.minutes} minutes: {line}"
        else:
            options = replace(args.run, device="cpu")
            steps = args.steps or train_app.default_schedule(args.schedule or "auto", options)[0]
            side = min(options.resolution or 512, 512)  # our videos are stored at 512 px
            cost = steps * (side / 256) ** 2
            assert cost <= MOST_STEPS_AT_256, f"README line trains {steps} steps at {side} px on a CPU: {line}"
        checked += 1
    assert checked >= 2, "the README shows no train line"


def test_prepare_takes_the_video_first(recorded):
    assert cli.main(["prepare", "talk.mp4", "--out", "data/talk", "--size", "256"]) == 0
    (_, kwargs), = recorded
    assert kwargs["video"] == Path("talk.mp4") and kwargs["out"] == Path("data/talk") and kwargs["size"] == 256


LONG_COMMANDS = ("prepare", "synth", "train", "eval", "render", "reenact", "orbit", "export", "demo", "bench")


@pytest.mark.parametrize("name", LONG_COMMANDS)
def test_long_commands_share_the_progress_flag(name, capsys):
    with pytest.raises(SystemExit) as exited:
        cli.main([name, "--help"])
    assert exited.value.code == 0
    help_text = " ".join(re.sub(r"[│╭╮╰╯─]", " ", capsys.readouterr().out).split())
    assert "--progress, --no-progress Show progress bars. (default: True)" in help_text, name


# --- running the cheap lines on tiny data ---------------------------------------------------------------


def _tiny_clip(video: Path, path: Path, frames: int = 6) -> Path:
    """The first frames of the shared test video, re-encoded (what `talk.mp4` stands for)."""
    import av

    with av.open(str(video)) as source, av.open(str(path), mode="w") as target:
        stream = None
        for index, frame in enumerate(source.decode(video=0)):
            if index == frames:
                break
            rgb = frame.to_ndarray(format="rgb24")[::2, ::2]  # half size: faster to decode and detect
            if stream is None:
                stream = target.add_stream("libx264", rate=Fraction(25))
                stream.height, stream.width = (s - s % 2 for s in rgb.shape[:2])
                stream.pix_fmt = "yuv420p"
            rgb = rgb[: stream.height, : stream.width]
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb.copy(), format="rgb24")):
                target.mux(packet)
        for packet in stream.encode():
            target.mux(packet)
    return path


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("readme")
    data = make_subject(root / "fixtures" / "data", subject=0, frames=8, size=48)
    driver = make_subject(root / "fixtures" / "driver", subject=1, frames=4, size=48, seed=1)
    run = make_run(data, root / "fixtures" / "run", steps=2)
    video, clip = shared_video("wojtek.mp4", required=False), root / "fixtures" / "talk.mp4"
    clip = _tiny_clip(video, clip) if video is not None else face_photo_video(clip)  # a user's clone: no video
    return {"root": root, "data": data, "driver": driver, "run": run, "clip": clip}


def _runnable(line: str, tiny: dict, workdir: Path) -> list[str] | None:
    """The README line with its placeholders mapped to fixtures and CHEAP options added (None: parse only)."""
    argv = shlex.split(line)[1:]
    name = command_of(argv)
    if not argv or any(line.startswith(f"geoavatar {p}") for p in PARSE_ONLY) or name == "":
        return None if argv else ["--help"]
    if "--driver-video" in argv:
        return None  # tracks a video with prepare's full settings (minutes); tests/test_reenact_video.py runs it
    fresh_run = name == "train" and "--resume" not in argv  # a new run goes to a new folder
    mapped = []
    for i, word in enumerate(argv):
        previous = argv[i - 1] if i else ""
        if word == "RUN":
            word = str(workdir / f"run{len(mapped)}" if fresh_run else tiny["run"])
        elif word == "DATA" or word == "DIR":
            word = str(tiny["driver"] if previous == "--driver" else tiny["data"])
        elif word == "talk.mp4":
            word = str(tiny["clip"])
        elif word == "data/talk/dataset":  # prepare's output; prepare is parse-only
            word = str(tiny["data"])
        elif word in PLACEHOLDERS and previous.startswith("--"):
            word = PLACEHOLDERS[word]
        mapped.append(word)
    if name == "train" and {"--resume", "--extend", "--minutes"} & set(argv):
        return None  # resuming/extending needs an unfinished run, --minutes a long one; parsed above
    return mapped + CHEAP.get(name, [])


def test_readme_lines_run_on_tiny_data(tiny, monkeypatch, capsys):
    workdir = tiny["root"] / "work"
    workdir.mkdir(exist_ok=True)
    monkeypatch.chdir(workdir)  # relative outputs of the README (data/subject0, head.png, ...) land here
    ran = []
    for line in COMMANDS:
        argv = _runnable(line, tiny, workdir)
        if argv is None or (command_of(argv) in ran and command_of(argv) not in RUN_EVERY_LINE):
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ShortVideoWarning)
            try:
                code = cli.main(argv)
            except SystemExit as exit:
                code = exit.code
        err = capsys.readouterr().err
        assert code in (0, None), f"README line failed: {line}\n  ran: geoavatar {shlex.join(argv)}\n  {err[-1500:]}"
        ran.append(command_of(argv) or argv[0])
    # (reenact is parsed, not run: the README drives it with --driver-video, which tests/test_reenact_video.py runs)
    assert {"synth", "train", "render", "orbit", "export", "view", "bench"} <= set(ran), ran
    assert (workdir / "runs" / "talk").is_dir()  # the own-video block's run, which the lines after it use
    shutil.rmtree(workdir / "data", ignore_errors=True)
