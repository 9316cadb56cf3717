"""`geoavatar export RUN --format web --out DIR`: a static folder that plays the animated avatar in a browser.

The front end of the animation layer's web clip (animation/sinks/web.py: the head posed per frame by the one posing
path, quantised, with its head pose code when the avatar's hair follows the head's turn; the view and orbit the page
opens with) fed by one of two sources:

    --split S (default test)          the run's frames of that split, as `geoavatar render` poses them
                                      (sources/split.py's SplitFrames: RunFrames' parameters and T rule)
    --driver DATA / --driver-video F  the driver's motion on the avatar, reenact's rules (--transfer as there;
                                      sources/driver.py's DriverMotion); a video is tracked first as reenact does
                                      (RUN/drivers/, reused)
    --audio FILE                      the avatar says the sound (sources/speech.py's SpeechFrames: the run's voice
                                      model, as `geoavatar speak`, --loudness as there); the folder carries the sound
                                      and the page plays it in step (audio.wav, docs/web_player.md)
"""

from __future__ import annotations

from pathlib import Path

from geoavatar.animation.expression_transfer import DEFAULT_TRANSFER, TransferMode, transfer_mode
from geoavatar.animation.play import play
# web_assets is also imported from here by benchmarks/web_player_bench.py
from geoavatar.animation.sinks.web import PosedClip, WebClip, web_assets  # noqa: F401
from geoavatar.animation.sources.driver import DriverMotion
from geoavatar.animation.sources.driver_video import track_driver
from geoavatar.animation.sources.split import SplitFrames
from geoavatar.apps.common import clip_timesteps
from geoavatar.errors import OptionError
from geoavatar.train.checkpoint import LoadedRun
from geoavatar.train.run_frames import RunFrames
from geoavatar.voice.model import loudness_tag

DEFAULT_FPS = 25.0


def split_clip(run: LoadedRun, frames: RunFrames, timesteps: list[int], show_progress: bool) -> PosedClip:
    """Each timestep posed with its parameters and T (RunFrames: the T rule), without the player's assets."""
    clip = WebClip(run, DEFAULT_FPS, "")
    play(run, SplitFrames(run, timesteps, frames=frames), [clip], progress=show_progress, desc="pose")
    return clip.clip


def export_web(run: LoadedRun, out: Path, split: str = "test", driver: Path | None = None,
               driver_video: Path | None = None, transfer: TransferMode | bool = DEFAULT_TRANSFER,
               fps: float | None = None,
               data: Path | None = None, flame_dir: Path | None = None, show_progress: bool = True,
               audio: Path | None = None, loudness: str = "own") -> Path:
    """Write the player folder `out` (complete or not at all); returns it."""
    if fps is not None and fps <= 0:
        raise OptionError(f"--fps must be positive, got {fps}")
    frames = RunFrames(run)
    if driver_video is not None:
        driver, video_fps, _ = track_driver(run, None, driver_video, flame_dir=flame_dir, progress=show_progress)
        fps = fps or video_fps
    if audio is not None:
        source = speech_frames(run, audio, fps or DEFAULT_FPS, loudness)
        name = f"speech {Path(audio).name}{loudness_tag(loudness, label=True)}"
        camera_timesteps = [frames.timesteps[0]]  # the avatar's camera
    elif driver is not None:
        mode = transfer_mode(transfer)
        source = DriverMotion(run, Path(driver), mode, fps or DEFAULT_FPS, frames)
        name = f"driver {Path(driver_video or driver).name} ({mode} transfer)"
        camera_timesteps = [frames.timesteps[0]]  # reenact's camera: the avatar's (first) neutral frame
    else:
        source = SplitFrames(run, clip_timesteps(run, split), fps or DEFAULT_FPS, frames)
        name, camera_timesteps = f"split {split}", None  # each frame's own dataset camera
    clip = WebClip(run, source.fps, name, camera_timesteps, data, out, audio=source.audio)
    play(run, source, [clip], progress=show_progress, desc="pose")
    return Path(out)


def speech_frames(run: LoadedRun, audio: Path, fps: float, loudness: str = "own"):
    """The speech source of a sound file (the run's voice model, hearing it by `loudness`: voice.LOUDNESS;
    VoiceModelError says how to get one)."""
    from geoavatar.animation.sources.speech import SpeechFrames
    from geoavatar.apps.speak import spoken_sound
    from geoavatar.voice import VoiceModel

    voice = VoiceModel.load(run.info.run_dir).hearing(loudness)
    sound, playback, _ = spoken_sound(audio)  # as `speak --audio` reads it
    return SpeechFrames(run, voice, sound, fps, playback)


def folder_size(folder: Path) -> int:
    return sum(f.stat().st_size for f in Path(folder).iterdir() if f.is_file())


__all__ = ["export_web", "folder_size", "split_clip"]
