"""A dataset's sound track: what the person said while the frames were filmed, aligned to the sample.

    DATASET/audio.wav    16-bit PCM mono at 16 kHz (geoavatar.sound.RATE): the video's sound, resampled once
    DATASET/audio.json   {"format", "rate", "samples", "source", "frame_times": {timestep: seconds}, "speech": {...}}

`frame_times` gives each timestep the time (seconds from audio.wav's first sample) at which its video frame was shown,
from the frame's own timestamp, so a video at 29.97 or 25 fps, or one whose picture starts later than its sound, stays
aligned; "speech" holds the voice-activity segments (geoavatar.sound.activity) and their total. `prepare` writes both
when the video has a sound track (`geoavatar synth --sound` too); a dataset without them has no sound, and its avatar
learns no voice.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoavatar.data.errors import DatasetError
from geoavatar.io.atomic import atomic_write_json
from geoavatar.sound import RATE, Sound, SoundError, read_sound, write_wav
from geoavatar.sound.activity import SpeechActivity

SOUND_FILE = "audio.wav"
SOUND_INFO = "audio.json"
SOUND_FORMAT = "geoavatar-dataset-sound"


@dataclass
class DatasetSound:
    sound: Sound  # at RATE
    frame_times: dict[int, float]  # timestep -> seconds from the sound's first sample
    activity: SpeechActivity
    source: str = ""

    def times(self, timesteps: list[int]) -> np.ndarray:
        """[T] seconds of these timesteps; DatasetError naming a timestep the sound does not time."""
        missing = [t for t in timesteps if t not in self.frame_times]
        if missing:
            raise DatasetError(f"{SOUND_INFO}: no frame time for timestep(s) {missing[:5]}")
        return np.array([self.frame_times[t] for t in timesteps], np.float64)


def write_dataset_sound(root: Path, sound: Sound, frame_times: dict[int, float], activity: SpeechActivity,
                        source: str = "") -> None:
    """Write audio.wav then audio.json (the json last: a dataset with the json has its whole sound)."""
    if sound.rate != RATE:
        raise ValueError(f"write_dataset_sound: the sound must be at {RATE} Hz, got {sound.rate}")
    root = Path(root)
    (root / SOUND_INFO).unlink(missing_ok=True)
    write_wav(root / SOUND_FILE, sound)
    atomic_write_json(root / SOUND_INFO, {
        "format": SOUND_FORMAT, "version": 1, "rate": RATE, "samples": int(len(sound.samples)), "source": source,
        "frame_times": {str(t): round(float(s), 6) for t, s in sorted(frame_times.items())},
        "speech": activity.to_json(),
    })


def remove_dataset_sound(root: Path) -> None:
    for name in (SOUND_INFO, SOUND_FILE):
        (Path(root) / name).unlink(missing_ok=True)


def has_dataset_sound(root: Path) -> bool:
    return (Path(root) / SOUND_INFO).is_file()


def read_dataset_sound(root: Path) -> DatasetSound | None:
    """The dataset's sound, or None when it has none; DatasetError naming the file when it is damaged, or the folder
    when it is not there (a run's dataset that moved is not one without sound)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: the dataset folder is not found (if it moved, give its new place with --data)")
    info_path = root / SOUND_INFO
    if not info_path.is_file():
        return None
    try:
        info = json.loads(info_path.read_text())
        if info.get("format") != SOUND_FORMAT:
            raise ValueError(f"format {info.get('format')!r}, expected {SOUND_FORMAT!r}")
        frame_times = {int(t): float(s) for t, s in info["frame_times"].items()}
        segments = [(float(a), float(b)) for a, b in info["speech"]["segments"]]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DatasetError(f"{info_path}: unreadable ({type(err).__name__}: {err})") from err
    try:
        sound = read_sound(root / SOUND_FILE, RATE, what="the dataset's sound")
    except SoundError as err:
        raise DatasetError(str(err)) from err
    if len(sound.samples) != int(info.get("samples", len(sound.samples))):
        raise DatasetError(f"{root / SOUND_FILE}: {len(sound.samples)} samples, {SOUND_INFO} says {info['samples']}")
    return DatasetSound(Sound(sound.samples, RATE, 0.0), frame_times, SpeechActivity(segments), info.get("source", ""))


__all__ = ["DatasetSound", "SOUND_FILE", "SOUND_INFO", "has_dataset_sound", "read_dataset_sound",
           "remove_dataset_sound", "write_dataset_sound"]
