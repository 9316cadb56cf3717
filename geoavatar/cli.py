"""`geoavatar <command> [<subcommand>] [options]`: one entry point, one typed function per job.

Each command is a plain function with typed, documented arguments living next to the code it drives;
tyro turns its signature into the option parser. Commands are imported lazily so that `--help` and
light commands start fast.
"""

from __future__ import annotations

import importlib
import sys
from typing import Callable, Union

# name -> "module:function", or a nested table for two-word commands ("head show").
CommandTable = dict[str, Union[str, "CommandTable"]]

COMMANDS: CommandTable = {
    "demo": "geoavatar.apps.demo:demo",
    "head": {
        "show": "geoavatar.apps.head_show:head_show",
    },
    "synth": "geoavatar.apps.synth:synth",
    "prepare": "geoavatar.apps.prepare:prepare",
    "coverage": "geoavatar.apps.coverage:coverage",
    "track": "geoavatar.apps.track:track",
    "train": "geoavatar.apps.train:train",
    "voice": "geoavatar.apps.voice:voice",
    "eval": "geoavatar.apps.eval:eval_runs",
    "ablate": "geoavatar.apps.ablate:ablate",
    "render": "geoavatar.apps.render_video:render",
    "reenact": "geoavatar.apps.reenact:reenact",
    "drive": "geoavatar.apps.drive:drive",
    "speak": "geoavatar.apps.speak:speak",
    "orbit": "geoavatar.apps.orbit:orbit",
    "export": "geoavatar.apps.export:export",
    "view": "geoavatar.apps.view:view",
    "bench": "geoavatar.apps.bench:bench",
}

_DESCRIPTIONS = {
    "demo": "The main job end to end on a generated subject: train, track the test frames, evaluate, render; writes report.md.",
    "head": "Head models: inspect the template, expressions and mouth structure.",
    "head show": "Render a contact sheet of a head model (front/side, expressions, open jaw).",
    "synth": "Generate a synthetic monocular dataset of a ground-truth actor (the embedded default).",
    "prepare": "Video -> dataset: crop, MediaPipe landmarks, head/neck masks, landmark + photometric tracking, overlay video.",
    "coverage": "Capture check of a dataset: head turns, jaw, expressions and gaze per split; advice; coverage.png.",
    "track": "Photometric tracking of an existing dataset on CPU: a copy with every frame's parameters refined.",
    "train": "Train a GeoAvatar (or an ablation preset) on a dataset; with speech in it, its voice model too.",
    "voice": "Learn (again) how the run's person moves their face when speaking, from its dataset's sound.",
    "eval": "Evaluate runs on the test split: MSE, PSNR, SSIM, LPIPS (+ mouth); Table 1 / ablation tables.",
    "ablate": "Train + evaluate datasets x ablation presets on Ray; the paper's ablation table and mouth crops.",
    "render": "Self re-enactment video of a run: ground truth | render | error map (mp4).",
    "reenact": "Cross re-enactment: drive a trained avatar with another dataset's or video's motion (mp4).",
    "drive": "Live driving from a webcam or a video: landmarks, online fit, the avatar rendered (mp4) or streamed to the browser player.",
    "speak": "Make the avatar say something new: a sound file, a text or a live microphone, through its voice model (mp4 with sound, browser player).",
    "orbit": "Novel views: a yaw/pitch sweep around the head (mp4).",
    "export": "Export as a standard 3DGS PLY (one frame, or a sequence as PLYs / npz), or a browser player of a clip (--format web).",
    "view": "The browser player of a run, with expression and jaw sliders posed in Python and streamed to it.",
    "bench": "Frames per second of the full animation path and of rasterization alone.",
}


def _resolve(target: str) -> Callable:
    module_name, func_name = target.split(":")
    return getattr(importlib.import_module(module_name), func_name)


def _print_help(table: CommandTable, prefix: str) -> None:
    print(f"usage: {prefix} <command> [options]\n")
    print("commands:")
    words = prefix.split()[1:]
    for name in table:
        key = " ".join([*words, name])
        print(f"  {name:<12} {_DESCRIPTIONS.get(key, '')}")
    print(f"\nRun '{prefix} <command> --help' for the options of a command.")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    table: CommandTable = COMMANDS
    prog = "geoavatar"
    while True:
        if not argv or argv[0] in ("-h", "--help"):
            _print_help(table, prog)
            return 0
        name = argv.pop(0)
        if name not in table:
            print(f"{prog}: unknown command '{name}'. Known: {', '.join(table)}", file=sys.stderr)
            return 2
        prog = f"{prog} {name}"
        entry = table[name]
        if isinstance(entry, dict):
            table = entry
            continue
        break

    from geoavatar.apps import call_command
    from geoavatar.errors import GeoAvatarError, one_line
    from geoavatar.runtime import setup_process

    setup_process()
    _notes_on_one_line()
    try:
        result = call_command(_resolve(entry), argv, prog)
    except GeoAvatarError as err:
        # the user's input is wrong, not the code: one line, no traceback (any other error keeps it)
        print(f"{prog}: {one_line(str(err))}", file=sys.stderr)
        return 2
    return int(result) if isinstance(result, int) else 0


def _notes_on_one_line() -> None:
    """GeoAvatar's own warnings (notes for the user) print as `geoavatar: note: <message>`, without the code line
    Python adds; every other warning as Python prints it."""
    import warnings

    from geoavatar.errors import GeoAvatarWarning, one_line

    python_show = warnings.showwarning
    if getattr(python_show, "geoavatar_notes", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, GeoAvatarWarning):
            print(f"geoavatar: note: {one_line(str(message))}", file=file or sys.stderr)
        else:
            python_show(message, category, filename, lineno, file, line)

    show.geoavatar_notes = True
    warnings.showwarning = show


if __name__ == "__main__":
    sys.exit(main())
