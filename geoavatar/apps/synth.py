"""`geoavatar synth`: generate a synthetic monocular dataset of a ground-truth actor."""

from __future__ import annotations

from pathlib import Path

from geoavatar.data.synth.generate import PREVIEW_FILE, SynthConfig, generate_dataset
from geoavatar.data.synth.subjects import NUM_SUBJECTS, get_subject
from geoavatar.data.synth.tracking import TrackingNoise


def synth(
    out: Path,
    subject: int = 0,
    frames: int = 300,
    size: int = 512,
    seed: int = 0,
    preview: bool = False,
    tracking_noise: bool = True,
    novel_views: bool = False,
    novel_every: int = 2,
    still_head: bool = False,
    sound: bool = False,
    progress: bool = True,
) -> None:
    """Generate a synthetic monocular head video with known ground truth, in the VHAP layout.

    A ground-truth actor (OpenHead with the subject's identity, plus hair volume, changed ears and
    glasses or a beard that the head model cannot express) talks, holds strong expressions while
    turning its head, blinks and looks around; the last 25 % of the frames (the last 350 from 700
    frames on) are a test segment with poses and expressions not seen before. Frames are rendered
    with the mesh rasterizer at 25 fps; flame_param/ holds tracker-like parameters (ground truth +
    error), flame_param_gt/ the exact ground truth.

    Args:
        out: Output folder. Must be new, empty, or an earlier `geoavatar synth` dataset (replaced).
        subject: Which actor, 0..2 (0: brown side-parted hair, protruding ears; 1: curly black hair,
            glasses; 2: auburn hair, beard, freckles).
        frames: Number of frames (25 fps).
        size: Image width and height in pixels.
        seed: Seed of the motion script and the tracker error (the actor is fixed by --subject).
        preview: Also write preview.png, a contact sheet across the sequence with side views.
        tracking_noise: Add tracker-like error to the written parameters (off: they equal the ground truth).
        novel_views: Also render test frames from extra cameras turned about the head (yaw +-30 and +-60,
            pitch +-20 degrees) into transforms_novel.json, the split `geoavatar eval --split novel` scores.
        novel_every: Every this many test frames get the novel views.
        still_head: The head never turns or nods (the face, the eyes and a slight sway still move): a video
            that `geoavatar coverage` should find lacking.
        sound: Also give the subject a voice: audio.wav / audio.json whose sound is a known function of its mouth
            (loudness and first formant from the jaw, second formant from the lips), so `geoavatar train` learns a
            voice model from it and `geoavatar speak` can make it say something new.
        progress: Show progress bars.
    """
    get_subject(subject)  # OptionError for --subject outside 0..NUM_SUBJECTS-1 (bad options: one line at the CLI)
    config = SynthConfig(
        subject=subject, frames=frames, size=size, seed=seed,
        tracking_noise=TrackingNoise(enabled=tracking_noise), novel_views=novel_views, novel_every=novel_every,
        still_head=still_head, sound=sound,
    )
    generate_dataset(Path(out), config, preview=preview, progress=progress)
    print(f"wrote {out}" + (f" (preview: {Path(out) / PREVIEW_FILE})" if preview else ""))


__all__ = ["synth", "NUM_SUBJECTS"]
