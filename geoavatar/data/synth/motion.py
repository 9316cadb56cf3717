"""The motion script of a synthetic actor: what the ground-truth head does, frame by frame.

It imitates the recording protocol of the paper's DynamicFace data (actors hold strong expressions
while slowly nodding and turning the head, plus talking), and ends with a test segment whose
expression/pose combinations never occur in the training part:

    training part (first `num_frames - test_frames` frames)
      30 %  talking: jaw 0-0.35 rad at syllable rate, lip shapes, small head motion
      70 %  held strong expressions, symmetric (smile, surprise, pucker, frown, grin, disgust, puffed
            cheeks, fear with wide eyes) and asymmetric (the mouth pulled hard to the left / right
            with a one-sided smile, a smirk) while the head sweeps yaw in [-22, +30] deg and pitch in
            [-12, +15] deg, roll +-3 deg
    test part (last `test_frames` frames)
            open-mouth speech with the teeth showing, in expression combinations the training part
            never has, at head poses inside the training ranges: talking while grinning (smile +
            mouth stretch, jaw never below 0.1 rad) turned to yaw -15 deg, then talking with the
            mouth pulled to the right under lowered brows (a pull and a frown, each seen in training,
            never together), then talking with raised brows and a wink turned to yaw +18 deg. The jaw
            stays within the training range
            (<= JAW_MAX), so what the test measures is the mouth and the expressions, not
            extrapolation to unseen head angles (an earlier script turned the test head beyond the
            training range; half of its frames were then equally wrong for every model).

Blinks every 2-4 s (at the dataset's fps) and gaze shifts every 1-2.5 s run through both parts.
Segment boundaries scale with the number of frames, so a 8-frame test video still passes through
every segment; event timing (blinks, syllables, saccades) is in seconds.

Everything here is numpy and deterministic for a given (num_frames, seed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# Held expressions of the training part: name -> (expression channel weights, jaw opening rad).
# Channel names are semantic; `geoavatar.data.synth.actor` maps them to the head model's modes.
TRAIN_EXPRESSIONS: tuple[tuple[str, dict[str, float], float], ...] = (
    ("smile", {"smile": 1.0, "cheek_raise": 0.5}, 0.0),
    ("surprise", {"brow_raise": 1.0, "eyes_wide": 0.8}, 0.22),
    ("pucker", {"pucker": 1.0}, 0.0),
    ("frown", {"brow_lower": 1.0, "mouth_frown": 0.8}, 0.0),
    ("grin", {"smile": 0.8, "mouth_stretch": 0.6}, 0.12),
    ("disgust", {"nose_wrinkle": 1.0, "upper_lip_raise": 0.8, "brow_lower": 0.4}, 0.05),
    # Asymmetric and strong shapes (issue #27: the expressive videos the paper is about pull the lips sideways,
    # puff the cheeks and widen the eyes): a hard sideways pull with a one-sided smile, each way; a smirk.
    ("pull_left", {"mouth_left": 1.0, "smile_left": 0.6}, 0.04),
    ("pull_right", {"mouth_right": 1.0, "smile_right": 0.6}, 0.04),
    ("puff", {"cheek_puff": 1.0, "lip_press": 0.6}, 0.0),
    ("fear", {"eyes_wide": 1.0, "brow_inner_raise": 1.0, "mouth_stretch": 0.5}, 0.15),
    ("smirk", {"smile_right": 1.0, "brow_raise": 0.4}, 0.0),
)

# Lip shapes mixed into talking (weights drawn per syllable).
TALK_SHAPES = ("pucker", "mouth_stretch", "smile", "upper_lip_raise", "lip_funnel")

# Head-pose ranges (degrees) of the training part, and the test extremes beyond them.
TRAIN_YAW_RANGE = (-22.0, 30.0)
TRAIN_PITCH_RANGE = (-12.0, 15.0)
TRAIN_ROLL_MAX = 3.0
TEST_YAW = (-15.0, 18.0)  # the two test segments' head yaw, inside TRAIN_YAW_RANGE
TEST_PITCH = (6.0, -6.0)  # their pitch, inside TRAIN_PITCH_RANGE
TEST_JAW_FLOOR = 0.1  # test speech keeps the mouth open at least this far (teeth visible)
JAW_MAX = 0.35


@dataclass
class Motion:
    """Ground-truth motion of one video, in semantic units (numpy, one row per frame)."""

    fps: float
    test_start: int  # first frame of the test segment
    yaw: np.ndarray  # [N] head yaw, radians (+ turns the face towards the subject's left = image right)
    pitch: np.ndarray  # [N] head pitch, radians (+ nods down)
    roll: np.ndarray  # [N] head roll, radians
    translation: np.ndarray  # [N, 3] head sway, metres (head frame: +x subject's left, +y up, +z forward)
    jaw: np.ndarray  # [N] jaw opening, radians (>= 0)
    gaze: np.ndarray  # [N, 2] eye yaw, pitch in radians (+pitch looks down, as the head)
    blink_left: np.ndarray  # [N] 0 open .. 1 closed
    blink_right: np.ndarray  # [N]
    expressions: dict[str, np.ndarray] = field(default_factory=dict)  # channel -> [N] weights
    segments: list[tuple[int, int, str]] = field(default_factory=list)  # (start, stop, label)

    @property
    def num_frames(self) -> int:
        return int(self.yaw.shape[0])


def held_out_frame_count(num_frames: int) -> int:
    """Frames in the held-out test segment, by the data layer's split rule (`geoavatar.data.splits`).

    The last 350 frames (INSTA protocol, as the paper) when the video has at least 700 frames, else
    the last 25 % (rounded up): so for every num_frames <= 700 but 700 itself, the last 25 %.
    """
    if num_frames < 2:
        raise ValueError(f"a synthetic video needs at least 2 frames, got {num_frames}")
    import warnings

    from geoavatar.data.splits import split_timesteps

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the short-video notice is expected here
        split = split_timesteps(list(range(num_frames)), source="synth")
    return len(split.test)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _hold_envelope(t: np.ndarray, start: float, stop: float, ramp: float) -> np.ndarray:
    """1 inside [start, stop] with smooth ramps of length `ramp` at both ends (t in any unit)."""
    ramp = max(ramp, 1e-6)
    return _smoothstep((t - start) / ramp) * _smoothstep((stop - t) / ramp)


def _smooth_noise(rng: np.random.Generator, n: int, correlation_frames: float) -> np.ndarray:
    """Temporally correlated noise with unit standard deviation: white noise through a Gaussian filter."""
    from scipy.ndimage import gaussian_filter1d

    white = rng.standard_normal(n + 8 * int(correlation_frames) + 8)
    smooth = gaussian_filter1d(white, sigma=max(correlation_frames, 1e-3), mode="wrap")
    smooth = smooth[: n]
    # Unit variance in expectation: the filter's gain on white noise is 1/sqrt(sum(g^2)).
    sigma = max(correlation_frames, 1e-3)
    radius = int(4 * sigma + 0.5)
    g = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    g = g / g.sum()
    return smooth / math.sqrt(float((g * g).sum()))


def _blink_track(rng: np.random.Generator, times: np.ndarray) -> np.ndarray:
    """Blinks every 2-4 s: 0.08 s closing, 0.16 s opening (a fast-close/slow-open lid profile)."""
    out = np.zeros_like(times)
    duration = float(times[-1]) if len(times) else 0.0
    t_blink = rng.uniform(0.6, 2.0)
    while t_blink < duration + 0.3:
        close, reopen = 0.08, 0.16
        rising = np.clip((times - (t_blink - close)) / close, 0.0, 1.0)
        falling = np.clip(1.0 - (times - t_blink) / reopen, 0.0, 1.0)
        out = np.maximum(out, np.where(times <= t_blink, rising, falling))
        t_blink += rng.uniform(2.0, 4.0)
    return out


def _gaze_track(rng: np.random.Generator, times: np.ndarray) -> np.ndarray:
    """Saccades every 1-2.5 s to targets within +-15 deg yaw, +-10 deg pitch; each saccade takes 0.06 s."""
    out = np.zeros((len(times), 2))
    duration = float(times[-1]) if len(times) else 0.0
    current = np.zeros(2)
    t_next = rng.uniform(0.3, 1.0)
    while t_next < duration:
        target = np.radians([rng.uniform(-15.0, 15.0), rng.uniform(-10.0, 10.0)])
        step = _smoothstep((times - t_next) / 0.06)[:, None]
        out = out + step * (target - current)
        current = target
        t_next += rng.uniform(1.0, 2.5)
    return out


def _talking(rng: np.random.Generator, times: np.ndarray, envelope: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Jaw opening at syllable rate (3.5-5.5 Hz) with random amplitude, and lip shapes per syllable."""
    jaw = np.zeros_like(times)
    shapes = {name: np.zeros_like(times) for name in TALK_SHAPES}
    if envelope.max() <= 0.0:
        return jaw, shapes
    duration = float(times[-1]) + 1e-3
    t = 0.0
    while t < duration:
        length = 1.0 / rng.uniform(3.5, 5.5)
        amp = rng.uniform(0.08, JAW_MAX)
        phase = np.clip((times - t) / length, 0.0, 1.0)
        bump = np.sin(np.pi * phase) ** 2 * ((times >= t) & (times < t + length))
        jaw = jaw + amp * bump
        shape = TALK_SHAPES[int(rng.integers(len(TALK_SHAPES)))]
        shapes[shape] = shapes[shape] + rng.uniform(0.3, 0.8) * bump
        t += length
    return jaw * envelope, {k: v * envelope for k, v in shapes.items()}


# Shares of the training part's normalised time: talking until _TALK_END, then the held expressions;
# _RAMP_U: the ramp length of the talking and head-sweep envelopes.
_TALK_END = 0.3
_RAMP_U = 0.04


@dataclass(frozen=True)
class _Timeline:
    """The clocks of one video, per frame: seconds, and the normalised time of its training and test parts."""

    train_frames: int
    test_frames: int
    times: np.ndarray  # [N] seconds
    frame: np.ndarray  # [N] frame index (float64)
    u: np.ndarray  # [N] 0..1 inside the training part (beyond 1 in the test part)
    w: np.ndarray  # [N] 0..1 inside the test part (negative in the training part)
    in_train: np.ndarray  # [N] bool
    in_test: np.ndarray  # [N] bool


def _timeline(num_frames: int, fps: float) -> _Timeline:
    """The clocks of a `num_frames` video whose last `held_out_frame_count` frames are the test part."""
    test_frames = held_out_frame_count(num_frames)
    train_frames = num_frames - test_frames
    frame = np.arange(num_frames, dtype=np.float64)
    in_train = frame < train_frames
    return _Timeline(
        train_frames=train_frames, test_frames=test_frames, times=np.arange(num_frames) / fps, frame=frame,
        u=frame / max(train_frames - 1, 1), w=(frame - train_frames) / max(test_frames - 1, 1),
        in_train=in_train, in_test=~in_train,
    )


def _add(tracks: dict[str, np.ndarray], name: str, values: np.ndarray) -> None:
    """Add `values` [N] to track `name` (a new track starts at zero).

    Every term goes through here in script order, so each track is the same sum, term by term, for a seed.
    """
    tracks[name] = tracks.get(name, np.zeros(values.shape[0])) + values


def _script_training_talk(rng: np.random.Generator, clock: _Timeline, pose: dict[str, np.ndarray],
                          channels: dict[str, np.ndarray]) -> None:
    """The first 30 % of the training part: talking with a little nodding and turning."""
    u = clock.u
    talk_env = _hold_envelope(u, -1.0, _TALK_END, _RAMP_U) * clock.in_train
    talk_jaw, talk_shapes = _talking(rng, clock.times, talk_env)
    _add(pose, "jaw", talk_jaw)
    for name, values in talk_shapes.items():
        _add(channels, name, values)
    _add(pose, "yaw", np.radians(8.0) * np.sin(2 * np.pi * u / _TALK_END * 0.5) * talk_env)
    _add(pose, "pitch", np.radians(5.0) * np.sin(2 * np.pi * u / _TALK_END) * talk_env)


def _script_held_expressions(rng: np.random.Generator, clock: _Timeline, pose: dict[str, np.ndarray],
                             channels: dict[str, np.ndarray]) -> np.ndarray:
    """The rest of the training part: TRAIN_EXPRESSIONS held one after another, in an order shuffled per seed.

    They share the part evenly. Returns the order [len(TRAIN_EXPRESSIONS)] (indices into TRAIN_EXPRESSIONS).
    """
    order = rng.permutation(len(TRAIN_EXPRESSIONS))
    slot = (1.0 - _TALK_END) / len(order)
    for k, idx in enumerate(order):
        _, weights, jaw_open = TRAIN_EXPRESSIONS[idx]
        start = _TALK_END + k * slot
        env = _hold_envelope(clock.u, start + 0.15 * slot, start + slot, 0.2 * slot) * clock.in_train
        strength = rng.uniform(0.85, 1.0)
        for name, value in weights.items():
            _add(channels, name, strength * value * env)
        _add(pose, "jaw", jaw_open * env)
    return order


def _script_head_sweep(clock: _Timeline, pose: dict[str, np.ndarray]) -> None:
    """Slow turns and nods over the held expressions (one yaw cycle, 1.5 pitch cycles), roll all through training."""
    u = clock.u
    sweep = np.clip((u - _TALK_END) / (1.0 - _TALK_END), 0.0, 1.0)
    sweep_env = _hold_envelope(u, _TALK_END, 1.0, _RAMP_U) * clock.in_train
    yaw_mid = np.radians(0.5 * (TRAIN_YAW_RANGE[0] + TRAIN_YAW_RANGE[1]))
    yaw_amp = np.radians(0.5 * (TRAIN_YAW_RANGE[1] - TRAIN_YAW_RANGE[0]))
    pitch_mid = np.radians(0.5 * (TRAIN_PITCH_RANGE[0] + TRAIN_PITCH_RANGE[1]))
    pitch_amp = np.radians(0.5 * (TRAIN_PITCH_RANGE[1] - TRAIN_PITCH_RANGE[0]))
    # envelope in [0, 1] times a value inside the range stays inside the range (which contains 0).
    _add(pose, "yaw", sweep_env * (yaw_mid + yaw_amp * np.sin(2 * np.pi * sweep)))
    _add(pose, "pitch", sweep_env * (pitch_mid + pitch_amp * np.cos(3 * np.pi * sweep)))
    _add(pose, "roll", np.radians(TRAIN_ROLL_MAX) * np.sin(2 * np.pi * 2.0 * u) * clock.in_train)


def _script_test_speech(rng: np.random.Generator, clock: _Timeline, pose: dict[str, np.ndarray],
                        channels: dict[str, np.ndarray]) -> None:
    """The test part: open-mouth speech in novel expression combinations, at poses inside the training ranges."""
    w, in_test = clock.w, clock.in_test
    ramp_w = 0.12
    # Ease in from the training part over at most 8 frames (short videos: straight to the pose).
    ease_frames = min(8.0, 0.1 * clock.test_frames)
    ease_in = _smoothstep((clock.frame - clock.train_frames + 1) / max(ease_frames, 1.0))
    first = _hold_envelope(w, -1.0, 0.4, ramp_w) * ease_in * in_test  # grinning, turned right
    pulled = _hold_envelope(w, 0.3, 0.65, ramp_w) * in_test  # mouth pulled right under lowered brows, head front
    second = _hold_envelope(w, 0.55, 2.0, ramp_w) * in_test  # raised brows, turned left
    speech = ease_in * in_test  # talking through the whole test part
    test_talk_jaw, test_talk_shapes = _talking(rng, clock.times, speech)
    # Syllables on top of an open mouth, scaled so that the jaw stays within the training range.
    _add(pose, "jaw", speech * TEST_JAW_FLOOR + test_talk_jaw * (JAW_MAX - TEST_JAW_FLOOR) / JAW_MAX)
    for name, values in test_talk_shapes.items():
        _add(channels, name, 0.5 * values)  # lighter lip shapes: the grin / brows carry the expression
    _add(channels, "smile", first * 0.9)
    _add(channels, "mouth_stretch", first * 0.6)
    _add(channels, "mouth_right", pulled * 0.9)
    _add(channels, "brow_lower", pulled * 0.8)
    _add(channels, "brow_raise", second * 0.8)
    _add(pose, "yaw", first * np.radians(TEST_YAW[0]) + second * np.radians(TEST_YAW[1]))
    _add(pose, "pitch", first * np.radians(TEST_PITCH[0]) + second * np.radians(TEST_PITCH[1]))
    _add(pose, "roll", np.radians(TRAIN_ROLL_MAX) * np.sin(2 * np.pi * w) * in_test)


def _eyelids(rng: np.random.Generator, clock: _Timeline, eyes_wide: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left and right lid closure [N] each: blinks through both parts, and a wink of the left eye in the test part.

    `eyes_wide` [N]: the expression channel; wide eyes blink less deeply.
    """
    wink = _hold_envelope(clock.w, 0.75, 0.92, 0.06) * clock.in_test
    blink = _blink_track(rng, clock.times)
    blink = blink * (1.0 - 0.5 * np.clip(eyes_wide, 0.0, 1.0))
    return np.clip(blink + wink, 0.0, 1.0), blink.copy()


def _sway(rng: np.random.Generator, num_frames: int, fps: float) -> np.ndarray:
    """A little translation sway of the head [N, 3], metres, correlated over 0.8 s."""
    corr = 0.8 * fps
    return np.stack(
        [0.006 * _smooth_noise(rng, num_frames, corr), 0.004 * _smooth_noise(rng, num_frames, corr),
         0.008 * _smooth_noise(rng, num_frames, corr)], axis=-1,
    )


def _segments(order: np.ndarray, train_frames: int, num_frames: int) -> list[tuple[int, int, str]]:
    """(start, stop, label) of the talking, each held expression (in `order`) and the test speech."""
    slot = (1.0 - _TALK_END) / len(order)
    segments = [(0, int(round(_TALK_END * (train_frames - 1))) + 1, "talking")]
    for k, idx in enumerate(order):
        a = int(round((_TALK_END + k * slot) * (train_frames - 1))) + 1
        b = int(round((_TALK_END + (k + 1) * slot) * (train_frames - 1))) + 1
        segments.append((min(a, train_frames), min(b, train_frames), f"hold:{TRAIN_EXPRESSIONS[idx][0]}"))
    segments.append((train_frames, num_frames, "test:speech"))
    return segments


def script_motion(num_frames: int, seed: int = 0, fps: float = 25.0, still_head: bool = False) -> Motion:
    """The motion of one synthetic video (deterministic for a given num_frames and seed).

    The test segment is the last `held_out_frame_count(num_frames)` frames: open-mouth speech in
    expression combinations outside the training part, at poses inside it (see the module docstring).
    `still_head`: the head never turns, nods or rolls (the sway, the face and the eyes move as scripted):
    the video a user makes who looks straight into the camera throughout.
    """
    clock = _timeline(num_frames, fps)
    rng = np.random.default_rng([seed, 0x5EED, num_frames])
    pose = {name: np.zeros(num_frames) for name in ("yaw", "pitch", "roll", "jaw")}  # each [N]
    channels: dict[str, np.ndarray] = {}  # expression channel -> [N] weights
    # The parts below draw from `rng` in this order: reordering them changes every seed's video.
    _script_training_talk(rng, clock, pose, channels)
    order = _script_held_expressions(rng, clock, pose, channels)
    _script_head_sweep(clock, pose)
    _script_test_speech(rng, clock, pose, channels)
    blink_left, blink_right = _eyelids(rng, clock, channels.get("eyes_wide", np.zeros(num_frames)))
    gaze = _gaze_track(rng, clock.times)
    translation = _sway(rng, num_frames, fps)
    yaw, pitch, roll = pose["yaw"], pose["pitch"], pose["roll"]
    if still_head:
        yaw, pitch, roll = np.zeros(num_frames), np.zeros(num_frames), np.zeros(num_frames)
    return Motion(
        fps=fps, test_start=clock.train_frames, yaw=yaw, pitch=pitch, roll=roll, translation=translation,
        jaw=np.clip(pose["jaw"], 0.0, None), gaze=gaze, blink_left=blink_left, blink_right=blink_right,
        expressions={k: v for k, v in sorted(channels.items())},
        segments=_segments(order, clock.train_frames, num_frames),
    )


__all__ = [
    "Motion", "script_motion", "held_out_frame_count", "TRAIN_EXPRESSIONS", "TALK_SHAPES",
    "TRAIN_YAW_RANGE", "TRAIN_PITCH_RANGE", "TRAIN_ROLL_MAX", "TEST_YAW", "TEST_PITCH", "TEST_JAW_FLOOR", "JAW_MAX",
]
