"""Sound: the one reading path (any rate, depth, container), the features (chunk-exact), the mp4 writer's sound track
(aligned to the frames) and bad sound files as one-line errors."""

from __future__ import annotations

import json
import wave
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_video
from geoavatar.sound import RATE, LogMelStream, Sound, SoundError, log_mel, read_sound, write_wav


def _write_pcm(path: Path, samples: np.ndarray, rate: int, width: int) -> Path:
    """A mono wav with `width` bytes a sample (1: unsigned 8-bit, 2: 16-bit)."""
    with wave.open(str(path), "wb") as out:
        out.setnchannels(1)
        out.setsampwidth(width)
        out.setframerate(rate)
        if width == 1:
            data = np.clip(np.round(samples * 127 + 128), 0, 255).astype(np.uint8)
        else:
            data = np.clip(np.round(samples * 32767), -32768, 32767).astype("<i2")
        out.writeframes(data.tobytes())
    return path


def _tone(seconds: float, rate: int, hz: float = 440.0, level: float = 0.5) -> np.ndarray:
    t = np.arange(int(seconds * rate)) / rate
    return (level * np.sin(2 * np.pi * hz * t)).astype(np.float32)


def _dominant_hz(sound: Sound) -> float:
    spectrum = np.abs(np.fft.rfft(sound.samples * np.hanning(len(sound.samples))))
    return float(np.fft.rfftfreq(len(sound.samples), 1.0 / sound.rate)[spectrum.argmax()])


def test_a_48khz_8bit_file_reads_as_16khz_float(tmp_path):
    path = _write_pcm(tmp_path / "low.wav", _tone(1.0, 48000, 440.0), 48000, 1)
    sound = read_sound(path)
    assert sound.rate == RATE and sound.samples.dtype == np.float32
    assert abs(len(sound.samples) - RATE) <= 64  # one second, within the resampler's delay
    assert abs(_dominant_hz(sound) - 440.0) < 3.0
    assert 0.4 < np.abs(sound.samples).max() < 0.6


def test_wav_round_trip_keeps_samples(tmp_path):
    original = Sound(_tone(0.5, RATE, 300.0), RATE)
    back = read_sound(write_wav(tmp_path / "a.wav", original))
    assert len(back.samples) == len(original.samples)
    assert np.abs(back.samples - original.samples).max() < 2e-4  # 16-bit rounding
    assert (tmp_path / "a.wav").stat().st_mode & 0o777 == 0o666 & ~_umask()


def _umask() -> int:
    import os

    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_bad_sound_files_are_one_line_errors(tmp_path):
    from geoavatar.io.video import write_mp4

    with pytest.raises(SoundError, match=r"--audio .*missing\.wav: file not found"):
        read_sound(tmp_path / "missing.wav", what="--audio")
    text = tmp_path / "notes.mp3"
    text.write_text("not a sound")
    with pytest.raises(SoundError, match=r"notes\.mp3: not a readable sound or video file"):
        read_sound(text, what="--audio")
    silent_video = write_mp4(tmp_path / "silent.mp4", [np.zeros((16, 16, 3), np.uint8)] * 3)
    with pytest.raises(SoundError, match=r"silent\.mp4: the file has no sound track"):
        read_sound(silent_video, what="--audio")
    for error in (SoundError("x"),):
        assert "\n" not in str(error)


def test_a_gap_in_the_sound_track_keeps_what_follows_at_its_time(tmp_path):
    """Packets missing from a track (a dropped stretch of a recording): the sound after them stays at its own time,
    the gap silent, rather than moving earlier by the gap."""
    import fractions

    import av

    samples = np.zeros(2 * RATE, np.float32)
    samples[RATE:RATE + 800] = _tone(0.05, RATE, 1000.0)  # a click at 1.0 s
    path = tmp_path / "gap.m4a"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("aac", rate=RATE, layout="mono")
        for k, first in enumerate(range(0, len(samples), 1024)):
            if 4 <= k < 9:  # 0.32 s of packets never written
                continue
            frame = av.AudioFrame.from_ndarray(samples[None, first:first + 1024], format="fltp", layout="mono")
            frame.sample_rate, frame.pts, frame.time_base = RATE, first, fractions.Fraction(1, RATE)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    sound = read_sound(path)
    click = sound.start + np.flatnonzero(np.abs(sound.samples) > 0.1)[0] / RATE
    assert click == pytest.approx(1.0, abs=0.005) and sound.seconds == pytest.approx(2.048, abs=0.01)


def test_log_mel_is_the_same_whatever_the_chunks():
    rng = np.random.default_rng(0)
    samples = (0.1 * rng.standard_normal(RATE)).astype(np.float32)
    whole = log_mel(samples)
    assert whole.shape == (len(samples) // 160 + 1, 40)
    stream, parts, at = LogMelStream(), [], 0
    while at < len(samples):
        size = int(rng.integers(1, 700))
        parts.append(stream.push(samples[at:at + size]))
        at += size
    parts.append(stream.finish())
    assert np.abs(np.concatenate(parts) - whole).max() < 1e-4


def test_log_mel_frame_f_is_centred_on_time_f_over_100():
    samples = np.zeros(RATE, np.float32)
    samples[8000] = 1.0  # a click at 0.5 s
    mel = log_mel(samples)
    assert int(mel.sum(1).argmax()) == 50


def test_mp4_sound_track_plays_with_its_frames(tmp_path):
    """Clicks at the times of frames 10, 30 and 55 land there in the written mp4, over a 25 fps and a 30 fps video."""
    import av

    from geoavatar.io.video import Mp4Writer

    for fps in (25.0, 30.0):
        samples = np.zeros(int(2.5 * RATE), np.float32)
        for frame in (10, 30, 55):
            at = int(round(frame / fps * RATE))
            samples[at:at + 80] = np.hanning(80)
        path = tmp_path / f"clicks{int(fps)}.mp4"
        count = int(2.5 * fps)
        with Mp4Writer(path, fps=fps, audio=Sound(samples, RATE)) as video:
            for _ in range(count):
                video.write(np.zeros((32, 32, 3), np.uint8))
        with av.open(str(path)) as container:
            assert [s.type for s in container.streams] == ["video", "audio"]
            frames = sum(1 for _ in container.decode(video=0))
        assert frames == count
        back = read_sound(path)
        assert abs(back.seconds - count / fps) < 0.07  # the sound ends with the last frame (one AAC block)
        lags = np.arange(-400, 401)
        heard = np.pad(back.samples, (0, max(0, len(samples) - len(back.samples))))
        score = [float(np.dot(samples[400:-400], heard[400 + k:len(samples) - 400 + k])) for k in lags]
        assert abs(int(lags[int(np.argmax(score))])) <= 16  # within 1 ms


def _prepare_sound(tmp_path: Path, video: Path, count: int, capsys) -> tuple[dict, str]:
    """prepare's sound stage on `video` (its first `count` frames kept): report.json's "sound", and what it said."""
    from geoavatar.io.atomic import atomic_write_npz
    from geoavatar.prep.pipeline import PrepareConfig, stage_sound

    out, work = tmp_path / video.stem, tmp_path / video.stem / ".prepare"
    work.mkdir(parents=True)
    (out / "dataset").mkdir()
    (out / "report.json").write_text("{}")
    atomic_write_npz(work / "frames.npz", source_index=np.arange(count), fps=np.array(25.0))
    atomic_write_npz(work / "landmarks.npz", keep=np.arange(count))
    stage_sound(PrepareConfig(video=video, out=out), work, None)
    return json.loads((out / "report.json").read_text())["sound"], capsys.readouterr().out


def test_prepare_keeps_the_sound_under_the_frames_and_says_what_it_lacks(tmp_path, capsys):
    """A sound track shorter than the picture: the frames after it are counted (report.json, one line) and the
    voice's data leaves them out; a sound track with no samples: the dataset is prepared without sound, in one line."""
    import av

    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.io.video import Mp4Writer

    short = tmp_path / "short.mp4"  # 2 s of picture, 1 s of sound
    with Mp4Writer(short, fps=25.0, audio=Sound(_tone(1.0, RATE), RATE)) as video:
        for _ in range(50):
            video.write(np.zeros((32, 32, 3), np.uint8))
    info, said = _prepare_sound(tmp_path, short, 50, capsys)
    assert info["track"] and 20 <= info["frames_without_sound"] <= 26, info
    assert "frames lie before or after the sound track" in said
    assert read_dataset_sound(tmp_path / "short" / "dataset").sound.seconds < 1.1

    empty = tmp_path / "empty.mkv"  # an audio stream that holds no packet
    with av.open(str(empty), "w") as container:
        picture = container.add_stream("libx264", rate=25)
        picture.width = picture.height = 32
        container.add_stream("pcm_s16le", rate=RATE, layout="mono")
        for _ in range(5):
            for packet in picture.encode(av.VideoFrame.from_ndarray(np.zeros((32, 32, 3), np.uint8))):
                container.mux(packet)
        for packet in picture.encode():
            container.mux(packet)
    info, said = _prepare_sound(tmp_path, empty, 5, capsys)
    assert info == {"track": False} and "the sound track cannot be used" in said


def test_speech_activity_finds_speech_and_silence():
    pytest.importorskip("silero_vad")
    from geoavatar.sound.activity import speech_activity

    silence = speech_activity(Sound(np.zeros(2 * RATE, np.float32), RATE))
    assert silence.speech_seconds == 0.0 and not silence.has_speech
    assert speech_activity(Sound(np.zeros(100, np.float32), RATE)).segments == []


@pytest.mark.parametrize("name", ["french.mp4"])
def test_speech_in_a_real_talking_video(name):
    from geoavatar.sound.activity import speech_activity

    video = shared_video(name)
    sound = read_sound(video).segment(0.0, 6.0)
    activity = speech_activity(sound)
    assert 3.0 < activity.speech_seconds <= 6.0


def test_sound_and_picture_stay_together_over_minutes(tmp_path):
    """Three minutes at 29.97 fps (a rate that rounds) with 24 kHz sound, as speak writes them: the frame count is
    video_frames' and the sound ends with the last frame; clicks at 5 s and 175 s are still where they were written."""
    from geoavatar.io.video import Mp4Writer
    from geoavatar.sound import video_frames

    rate, fps, seconds = 24000, 30000 / 1001, 180.0
    samples = np.zeros(int(seconds * rate), np.float32)
    for at in (5.0, 175.0):
        samples[int(at * rate):int(at * rate) + 120] = np.hanning(120)
    count = video_frames(seconds, fps)
    path = tmp_path / "long.mp4"
    with Mp4Writer(path, fps=fps, audio=Sound(samples, rate), preset="ultrafast") as video:
        for _ in range(count):
            video.write(np.zeros((16, 16, 3), np.uint8))
    assert count == 5395 and video.frames == count
    back = read_sound(path)
    assert abs(back.seconds - count / fps) < 0.07  # the sound ends with the last frame (one AAC block)
    clicks = np.flatnonzero(np.abs(back.samples) > 0.3) / RATE + back.start
    for at in (5.0, 175.0):
        assert np.min(np.abs(clicks - at - 60 / rate)) < 0.002  # the click's peak, within 2 ms after three minutes
