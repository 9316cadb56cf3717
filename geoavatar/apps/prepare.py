"""`geoavatar prepare`: turn a monocular video into a tracked dataset (frames, masks, head-model parameters)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Literal, Optional

import tyro

from geoavatar.prep.errors import PrepareError
from geoavatar.prep.pipeline import PrepareConfig, run_prepare
from geoavatar.runtime import show_native_logs


# The input video: the subject of the command, first and positional (`geoavatar prepare talk.mp4 --out data/talk`).
VideoPath = Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="VIDEO")]


def prepare(
    video: VideoPath,
    out: Path,
    head: Literal["openhead", "flame"] = "openhead",
    size: int = 512,
    fps: Optional[float] = None,
    max_frames: Optional[int] = None,
    missing: Literal["interpolate", "drop"] = "interpolate",
    test_fraction: float = 0.2,
    flame_dir: Optional[Path] = None,
    flame_landmarks: Optional[Path] = None,
    static_offset: bool = True,
    photometric: bool = True,
    overlay: bool = True,
    workers: Optional[int] = None,
    progress: bool = True,
    verbose: bool = False,
) -> int:
    """Prepare a dataset from a monocular head video: crop, landmarks, masks, head-model tracking (a landmark fit,
    then a photometric refinement of every frame unless --no-photometric).

    Writes OUT/dataset (VHAP / GaussianAvatars layout, ready for `geoavatar train --data OUT/dataset`),
    OUT/overlay.mp4 (tracked mesh and landmarks over the frames: green MediaPipe, red model; frames without a
    face flagged), OUT/report.json (per-frame landmark reprojection error and photometric residual, frames
    without a face, the capture check) and OUT/coverage.png; prints the capture check's verdict: which head turns,
    mouth openings, expressions and gaze the video covers, whether its test segment leaves what training saw,
    and what to film differently. Stages are resumable: a re-run skips the stages whose outputs are complete
    (OUT/.prepare/).

    Args:
        video: Input video (any container/codec PyAV decodes; rotation metadata is honoured).
        out: Output folder.
        head: Head model to track: openhead (built in) or flame (your FLAME files, see --flame-dir).
        size: Side in pixels of the square, face-centred crop written to the dataset.
        fps: Subsample the video to this frame rate (default: every frame).
        max_frames: Use at most this many frames (after subsampling).
        missing: Frames where no face is found: interpolate their landmarks, or drop them.
        test_fraction: The last fraction of frames forms the test split.
        flame_dir: Folder with FLAME (flame2023.pkl or generic_model.pkl, FLAME_masks.pkl) for --head flame.
        flame_landmarks: FLAME's MediaPipe landmark embedding (default FLAME_DIR/mediapipe_landmark_embedding.npz).
        static_offset: Fit one smooth static offset of the mesh for the person (VHAP's static_offset),
            written to the dataset; without it only the head model's identity modes adapt.
        photometric: After the landmark fit, refine every frame photometrically (a mesh-bound appearance
            model rendered with the CPU rasterizer against the masked crops, landmarks kept as a term);
            --no-photometric writes the landmark fit as is (faster). Re-running with it on over a
            --no-photometric folder reuses every earlier stage and adds the photometric one.
        overlay: Write OUT/overlay.mp4.
        workers: Worker processes (default: one per core this process may use, at most 8; each holds up to
            0.9 GB). The dataset does not depend on it.
        progress: Show progress bars.
        verbose: Also show the log lines of the libraries underneath (MediaPipe, TensorFlow Lite), which are
            kept out of the terminal otherwise.
    """
    config = PrepareConfig(
        video=video, out=out, head=head, size=size, fps=fps, max_frames=max_frames, missing=missing,
        test_fraction=test_fraction, flame_dir=flame_dir, flame_landmarks=flame_landmarks,
        static_offset=static_offset, photometric=photometric, overlay=overlay, workers=workers,
        progress=progress,
    )
    try:
        _check_out(Path(out))
        with show_native_logs(verbose):
            dataset = run_prepare(config)
    except PrepareError as err:
        print(f"geoavatar prepare: {err}", file=sys.stderr)
        return 2
    overlay_line = f"overlay: {Path(out) / 'overlay.mp4'}\n" if overlay else ""
    print(f"dataset: {dataset}\n{overlay_line}report: {Path(out) / 'report.json'}")
    print(capture_verdict(Path(out)))
    return 0


def _check_out(out: Path) -> None:
    """PrepareError naming --out when OUT cannot be a folder: it, or a folder it would be made in, is a file."""
    for path in (out, *out.parents):
        if path.exists():
            if not path.is_dir():
                what = "is a file" if path == out else f"{path} is a file"
                raise PrepareError(f"--out {out}: {what}, not a folder (prepare writes a folder: dataset/, "
                                   "report.json, overlay.mp4)")
            return


def capture_verdict(out: Path) -> str:
    """The capture check's verdict from OUT/report.json (a re-run that skipped every stage prints it too)."""
    import json

    try:
        return json.loads((out / "report.json").read_text())["capture"]["verdict"]
    except (OSError, ValueError, KeyError, TypeError):
        return "capture check: not in report.json (run prepare again to add it)"
