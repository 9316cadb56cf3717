"""The sound track of a generated subject: a voice whose sound is a known function of its mouth (`synth --sound`).

    sound, voiced = speech_sound(motion)          # Sound at 16 kHz; [n] bool where the voice sounds
    sound = new_speech(seconds=4, seed=1)         # a clip of the same voice saying something the subject never said

A source-filter voice (additive synthesis: the harmonics of a glottal pulse train shaped by formant resonances):
    loudness   proportional to the jaw opening (silent when the jaw is closed: below JAW_VOICED rad)
    F1         rises with the jaw opening (250 Hz closed -> ~950 Hz at 0.35 rad), as an open vowel's does
    F2         falls with rounded lips (pucker, funnel), rises with spread ones (smile, stretch)
    pitch      115 Hz with a slow intonation curve
So a model that hears this sound can recover the jaw and the lip shapes frame by frame; a model whose sound is
shifted against the frames cannot (tests/test_voice.py shows both).
"""

from __future__ import annotations

import numpy as np

from geoavatar.sound import RATE, Sound
from geoavatar.sound.activity import SpeechActivity

JAW_VOICED = 0.02  # radians: below this opening the voice is silent
F0 = 115.0
ROUNDED = ("pucker", "lip_funnel")
SPREAD = ("smile", "mouth_stretch")


def _at_samples(values: np.ndarray, fps: float, count: int) -> np.ndarray:
    """A per-frame track [N] (frame k shown at k / fps) at every sample time, linearly interpolated."""
    frame_times = np.arange(len(values)) / fps
    return np.interp(np.arange(count) / RATE, frame_times, values)


def _resonance(freq: np.ndarray, centre: np.ndarray, bandwidth: float) -> np.ndarray:
    return 1.0 / np.sqrt(1.0 + ((freq - centre) / bandwidth) ** 2)


def synthesise(jaw: np.ndarray, rounding: np.ndarray, spread: np.ndarray, fps: float, seed: int = 0
               ) -> tuple[Sound, np.ndarray]:
    """The voice of per-frame jaw openings [N] (radians), lip rounding and spreading [N] (0..1); returns the sound and
    where it is voiced ([n] bool)."""
    count = int(round(len(jaw) / fps * RATE))
    rng = np.random.default_rng([seed, 0x50D])
    opening = _at_samples(np.asarray(jaw, np.float64), fps, count)
    amplitude = np.clip((opening - JAW_VOICED) / 0.3, 0.0, 1.0)  # [n]
    f1 = 250.0 + 2000.0 * np.clip(opening, 0.0, 0.35)
    f2 = 1500.0 - 700.0 * _at_samples(np.clip(rounding, 0, 1), fps, count) \
        + 700.0 * _at_samples(np.clip(spread, 0, 1), fps, count)
    t = np.arange(count) / RATE
    pitch = F0 * (1.0 + 0.08 * np.sin(2 * np.pi * 0.4 * t + rng.uniform(0, 6.3)))  # [n] Hz
    phase = 2 * np.pi * np.cumsum(pitch) / RATE
    signal = np.zeros(count)
    for k in range(1, int(4000 / F0)):  # harmonics below 4 kHz
        freq = k * pitch
        gain = (_resonance(freq, f1, 90.0) + 0.7 * _resonance(freq, f2, 120.0)
                + 0.3 * _resonance(freq, 2600.0, 200.0)) / k ** 0.7
        signal += gain * np.sin(k * phase)
    signal = signal / (np.abs(signal).max() + 1e-9)
    samples = 0.5 * amplitude * signal + 0.002 * rng.standard_normal(count)  # a little room noise
    return Sound(samples.astype(np.float32), RATE, 0.0), amplitude > 0.02


def _channel(motion, names: tuple[str, ...]) -> np.ndarray:
    return np.clip(sum((motion.expressions.get(n, np.zeros(motion.num_frames)) for n in names),
                       np.zeros(motion.num_frames)), 0.0, 1.0)


def speech_sound(motion, seed: int = 0) -> tuple[Sound, SpeechActivity]:
    """The sound a generated subject makes with its scripted mouth, and where it speaks."""
    sound, voiced = synthesise(motion.jaw, _channel(motion, ROUNDED), _channel(motion, SPREAD), motion.fps, seed)
    return sound, activity_of(voiced)


def activity_of(voiced: np.ndarray) -> SpeechActivity:
    """Speech segments of a voiced mask at RATE (gaps under 0.2 s bridged, as a voice-activity detector would)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], voiced.astype(np.int8), [0]])))
    segments = [(a / RATE, b / RATE) for a, b in zip(edges[::2], edges[1::2])]
    merged: list[tuple[float, float]] = []
    for start, stop in segments:
        if merged and start - merged[-1][1] < 0.2:
            merged[-1] = (merged[-1][0], stop)
        else:
            merged.append((start, stop))
    return SpeechActivity(merged)


def new_speech(seconds: float, seed: int, fps: float = 25.0) -> Sound:
    """A clip of the generated voice saying something new: syllables at 3.5-5.5 Hz with random openings and lip
    shapes, as the subjects' talking is scripted (data/synth/motion.py), from another seed."""
    from geoavatar.data.synth.motion import JAW_MAX

    rng = np.random.default_rng([seed, 0x7A1C])
    count = int(round(seconds * fps))
    jaw, rounding, spread = np.zeros(count), np.zeros(count), np.zeros(count)
    times = np.arange(count) / fps
    t = 0.3
    while t < seconds - 0.3:
        length = 1.0 / rng.uniform(3.5, 5.5)
        bump = np.sin(np.pi * np.clip((times - t) / length, 0, 1)) ** 2 * ((times >= t) & (times < t + length))
        jaw += rng.uniform(0.08, JAW_MAX) * bump
        (rounding if rng.random() < 0.5 else spread)[:] += rng.uniform(0.3, 0.8) * bump
        t += length + (rng.uniform(0.2, 0.5) if rng.random() < 0.15 else 0.0)  # now and then a pause
    return synthesise(jaw, rounding, spread, fps, seed)[0]


__all__ = ["activity_of", "new_speech", "speech_sound", "synthesise"]
