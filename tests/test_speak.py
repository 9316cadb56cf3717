"""`geoavatar speak` and the speech sources: an mp4 with its sound (one frame per 1/fps of sound), text through an
offline synthesiser, the web export with sound, the live path (a file played in real time, the browser's microphone)
in real Chromium, and bad input as one line."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import threading
import time
import warnings

import numpy as np
import pytest

from geoavatar.data.splits import ShortVideoWarning
from geoavatar.web.browser import AUTOPLAY, browser_missing, chromium_page, fake_microphone

FPS = 25.0
browser = pytest.mark.skipif(browser_missing() is not None, reason=f"browser tests: {browser_missing()}")


@pytest.fixture(scope="module")
def speaker(tmp_path_factory):
    """A generated subject with its voice, a run of its untrained state and a quickly learned voice model."""
    from apps_fixtures import make_untrained_run

    from geoavatar.data.synth.generate import SynthConfig, generate_dataset
    from geoavatar.train.checkpoint import open_run
    from geoavatar.voice.config import VoiceConfig
    from geoavatar.voice.train import train_voice

    root = tmp_path_factory.mktemp("speak")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        data = generate_dataset(root / "data", SynthConfig(frames=120, size=32, sound=True, workers=1),
                                progress=False)
    run_dir = make_untrained_run(data, root / "run")
    run = open_run(run_dir, "cpu")
    train_voice(run, VoiceConfig(steps=60, validate_every=30), log=lambda _: None).save(run_dir)
    return root, run_dir


@pytest.fixture(scope="module")
def clip(speaker):
    """3.1 s of the subject's voice saying something new, as a 44.1 kHz wav (a file as users have them)."""
    from geoavatar.data.synth.sound import new_speech
    from geoavatar.sound.track import resample, write_wav

    return write_wav(speaker[0] / "new.wav", resample(new_speech(3.1, seed=5), 44100))


def _streams(path):
    import av

    with av.open(str(path)) as container:
        frames = sum(1 for _ in container.decode(video=0))
        audio = container.streams.audio[0]
        return frames, float(audio.duration * audio.time_base)


def test_speak_writes_one_frame_per_frame_of_sound_with_the_sound(speaker, clip):
    from geoavatar.cli import main

    out = speaker[0] / "talk.mp4"
    assert main(["speak", str(speaker[1]), "--audio", str(clip), "--out", str(out), "--no-progress"]) == 0
    frames, seconds = _streams(out)
    from geoavatar.sound import read_sound

    assert frames == math.ceil(read_sound(clip).seconds * FPS)
    assert abs(seconds - frames / FPS) <= 1.0 / FPS  # the sound lasts as long as the frames


def test_speak_a_text(speaker):
    from geoavatar.apps.speak import speak
    from geoavatar.sound.synthesis import ENGINES

    import shutil

    if not any(shutil.which(engine) for engine in ENGINES):
        pytest.skip("no offline speech synthesiser (espeak-ng, flite) installed")
    out = speaker[0] / "text.mp4"
    assert speak(speaker[1], text="Hello, this is my avatar.", out=out, progress=False) == 0
    frames, seconds = _streams(out)
    assert frames > 20 and abs(seconds - frames / FPS) <= 1.0 / FPS


def test_speech_moves_the_mouth_and_the_head(speaker, clip):
    """Frames of a speech source: the jaw opens and closes with the syllables, the head moves (the idle motion)."""
    from geoavatar.animation.sources.speech import SpeechFrames
    from geoavatar.sound import read_sound
    from geoavatar.train.checkpoint import open_run
    from geoavatar.voice import VoiceModel

    run = open_run(speaker[1], "cpu")
    source = SpeechFrames(run, VoiceModel.load(speaker[1]), read_sound(clip), FPS)
    frames = list(source)
    assert [f.index for f in frames] == list(range(len(source))) and all(f.T is None for f in frames)
    jaw = np.array([float(f.params.jaw_pose[0, 0]) for f in frames])
    rotation = np.stack([f.params.rotation[0].numpy() for f in frames])
    assert jaw.std() > 0.02  # radians: the mouth moves
    assert rotation.std(0).max() > 1e-3  # and so does the head


@pytest.mark.parametrize("case", ["no voice model", "no sound track", "not a sound", "missing", "no source",
                                  "microphone without view", "video loudness of a text", "out is a folder",
                                  "text says nothing", "not a flite voice", "eval option not with speech"])
def test_bad_input_is_one_line(speaker, clip, tmp_path, capsys, case):
    from apps_fixtures import make_subject, make_untrained_run

    from geoavatar.cli import main
    from geoavatar.io.video import write_mp4

    run = str(speaker[1])
    if case == "no voice model":
        quiet = make_untrained_run(make_subject(tmp_path / "quiet", frames=8), tmp_path / "quiet_run")
        argv, expected = ["speak", str(quiet), "--audio", str(clip)], "has no voice model"
    elif case == "no sound track":
        video = write_mp4(tmp_path / "silent.mp4", [np.zeros((16, 16, 3), np.uint8)] * 3)
        argv, expected = ["speak", run, "--audio", str(video)], "--audio .*silent.mp4: the file has no sound track"
    elif case == "not a sound":
        text = tmp_path / "notes.wav"
        text.write_text("hello")
        argv, expected = ["speak", run, "--audio", str(text)], "notes.wav: not a readable sound"
    elif case == "missing":
        argv, expected = ["speak", run, "--audio", str(tmp_path / "nope.wav")], "nope.wav: file not found"
    elif case == "no source":
        argv, expected = ["speak", run], "give one thing to say"
    elif case == "microphone without view":
        argv, expected = ["speak", run, "--microphone"], "--microphone needs --view"
    elif case == "out is a folder":
        (tmp_path / "talk.mp4").mkdir()
        argv, expected = ["speak", run, "--audio", str(clip), "--out", str(tmp_path / "talk.mp4")], "is a folder"
    elif case in ("text says nothing", "not a flite voice"):
        engine = "espeak-ng" if case == "text says nothing" else "flite"
        if not shutil.which(engine):
            pytest.skip(f"{engine} is not installed")
        argv, expected = (["speak", run, "--text", "...", "--tts", engine], "espeak-ng said nothing for '...'") if (
            engine == "espeak-ng") else (["speak", run, "--text", "bonjour", "--tts", "flite", "--tts-voice", "fr"],
                                         "--tts-voice fr: not one of flite's voices")
    elif case == "eval option not with speech":
        argv, expected = ["eval", run, "--speech", "--lpips-net", "alex"], "--lpips-net: not with --speech"
    else:
        argv, expected = ["speak", run, "--text", "hello", "--loudness", "video"], "--loudness video is for a recording"
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    import re

    assert re.search(expected, err), err


def test_a_tenth_of_a_second_and_an_8_bit_48khz_file_still_speak(speaker, tmp_path):
    import wave

    from geoavatar.apps.speak import speak

    rate = 48000
    t = np.arange(int(0.1 * rate)) / rate
    path = tmp_path / "short.wav"
    with wave.open(str(path), "wb") as out:
        out.setnchannels(1)
        out.setsampwidth(1)
        out.setframerate(rate)
        out.writeframes(np.round(127 * 0.5 * np.sin(2 * np.pi * 220 * t) + 128).astype(np.uint8).tobytes())
    assert speak(speaker[1], audio=path, out=tmp_path / "short.mp4", progress=False) == 0
    assert _streams(tmp_path / "short.mp4")[0] == math.ceil(0.1 * FPS)
    # played as a live source, shorter than the look-ahead: the same frames once the sound ends, the sound at 24 kHz
    assert speak(speaker[1], audio=path, live=True, out=tmp_path / "live.mp4", fps=FPS, status=False) == 0
    assert _streams(tmp_path / "live.mp4")[0] == math.ceil(0.1 * FPS)
    import av

    with av.open(str(tmp_path / "live.mp4")) as container:
        assert container.streams.audio[0].codec_context.sample_rate == 24000


@browser
def test_the_web_export_plays_the_speech_with_its_sound(speaker, clip, tmp_path):
    import json

    from geoavatar.cli import main
    from geoavatar.web.browser import static_server, wait_drawn

    out = tmp_path / "player"
    assert main(["export", str(speaker[1]), "--format", "web", "--audio", str(clip), "--out", str(out),
                 "--no-progress"]) == 0
    from geoavatar.sound import read_sound

    seconds = read_sound(clip).seconds
    manifest = json.loads((out / "avatar.json").read_text())
    assert manifest["clip"]["frames"] == math.ceil(seconds * FPS)
    assert manifest["clip"]["audio"]["seconds"] == pytest.approx(seconds, abs=1e-3)
    with static_server(out) as url, chromium_page(96, 96, args=AUTOPLAY) as page:
        page.goto(url)
        wait_drawn(page, 0)
        page.wait_for_function("document.getElementById('sound').currentTime > 0.2", timeout=60_000)
        shown = page.evaluate("() => new Promise((done) => requestAnimationFrame(() => done(["
                              "document.getElementById('sound').currentTime, window.geoavatar.player.frame])))")
    audio_time, frame = shown
    assert abs(frame - math.floor(audio_time * FPS)) <= 1


def test_the_web_export_hears_the_sound_by_the_chosen_loudness(speaker, tmp_path, capsys):
    """`export --audio --loudness video` plays what `speak --loudness video` says: a quieter recording of the voice
    moves the mouth less than by its own statistics, and the manifest names the choice."""
    from geoavatar.cli import main
    from geoavatar.data.synth.sound import new_speech
    from geoavatar.sound.track import write_wav

    speech = new_speech(3.0, seed=7)
    quiet = write_wav(tmp_path / "quiet.wav", dataclasses.replace(speech, samples=speech.samples * 0.1))
    clips = {}
    for loudness in ("own", "video"):
        out = tmp_path / loudness
        assert main(["export", str(speaker[1]), "--format", "web", "--audio", str(quiet), "--loudness", loudness,
                     "--out", str(out), "--no-progress"]) == 0
        clips[loudness] = json.loads((out / "avatar.json").read_text())["clip"], (out / "clip.bin").read_bytes()
    assert clips["own"][0]["source"] == "speech quiet.wav"
    assert clips["video"][0]["source"] == "speech quiet.wav (video loudness)"
    assert clips["own"][1] != clips["video"][1]
    assert main(["export", str(speaker[1]), "--format", "web", "--loudness", "video"]) == 2
    assert capsys.readouterr().err.strip().endswith("--loudness goes with --audio")


def _live(speaker, sound_input, live, seconds, callbacks=None):
    """speak's live path in a thread (start_viewer + speak_live), a Chromium page on it here; returns (source, page
    stats)."""
    from geoavatar.apps.speak import speak_live
    from geoavatar.apps.view import start_viewer
    from geoavatar.train.checkpoint import open_run
    from geoavatar.voice import VoiceModel

    run = open_run(speaker[1], "cpu")
    viewer = start_viewer(run, port=0, expr_sliders=0, live=live, **(callbacks or {}))
    result, args = {}, fake_microphone(sound_input.wav) if hasattr(sound_input, "wav") else []

    def work():
        try:
            result["source"] = speak_live(run, VoiceModel.load(speaker[1]), sound_input, FPS, 0, viewer,
                                          max_seconds=seconds, status=False)
        except BaseException as err:  # raised here, in the test's thread
            result["error"] = err

    try:
        with chromium_page(96, 96, args=args) as page:
            page.goto(viewer.url)
            page.wait_for_function("window.geoavatar && window.geoavatar.stats.ready", timeout=60_000)
            thread = threading.Thread(target=work, daemon=True)
            thread.start()
            thread.join(timeout=60 + seconds * 3)
            time.sleep(0.5)
            # the frame still on the GPU (software GL: ~0.5 s), so that its latency is counted
            page.wait_for_function("() => { const s = window.geoavatar.stats; return s.drawn === s.finished; }",
                                   timeout=30_000)
            stats = page.evaluate("window.geoavatar.stats")
    finally:
        viewer.stop()
    if "error" in result:
        raise result["error"]
    return result["source"], stats, viewer


def _drawn_without_a_queue(stats):
    """The page drew meshes posed from sound, each timed to the GPU's end of it, and never had more than one frame
    on the GPU: software GL draws a frame in ~0.5 s here, so most meshes are skipped rather than queued."""
    latency = stats["soundToPicture"]
    assert latency["count"] >= 1 and 0 < latency["p50"] <= latency["p95"], latency
    assert stats["finished"] >= 1 and stats["drawn"] - stats["finished"] <= 1, stats


@browser
def test_a_sound_file_played_live_drives_the_browser(speaker, clip):
    from geoavatar.animation.sources.speech import RealTimeSound
    from geoavatar.sound import read_sound

    source, stats, viewer = _live(speaker, RealTimeSound(read_sound(clip)), True, 2.0)
    assert source.stats.frames >= 10 and viewer.server.sent >= 10
    assert stats["received"] >= 10  # meshes that reached the page as the sound arrived
    _drawn_without_a_queue(stats)


@browser
def test_the_browsers_microphone_drives_the_avatar(speaker, clip, tmp_path):
    from geoavatar.animation.sources.speech import MicrophoneSound

    microphone = MicrophoneSound()
    microphone.wav = clip  # Chromium's fake device plays it
    callbacks = {"on_audio": microphone.on_audio, "on_microphone_error": microphone.on_error}
    source, stats, _ = _live(speaker, microphone, "speak", 2.0, callbacks)
    assert microphone.chunks_received >= 90  # 2 s of 20 ms chunks
    assert source.stats.frames >= 10
    assert stats["microphoneChunks"] >= 90
    _drawn_without_a_queue(stats)


@browser
def test_a_page_without_a_microphone_ends_speak_with_one_line(speaker):
    from geoavatar.animation.sources.speech import MicrophoneError, MicrophoneSound

    microphone = MicrophoneSound()
    callbacks = {"on_audio": microphone.on_audio, "on_microphone_error": microphone.on_error}
    with pytest.raises(MicrophoneError, match=r"^--microphone: microphone: ") as error:
        _live(speaker, microphone, "speak", 30.0, callbacks)
    assert "\n" not in str(error.value)


def test_eval_speech_with_the_videos_loudness_writes_its_own_report(speaker, capsys):
    from geoavatar.cli import main

    run = speaker[1]
    assert main(["eval", str(run), "--speech", "--loudness", "video", "--max-frames", "2", "--no-progress"]) == 0
    report = json.loads((run / "eval" / "speech@video-loudness" / "metrics.json").read_text())
    assert "training sound's speech statistics" in report["settings"]["normalisation"]
    assert not (run / "eval" / "speech").exists()  # the default report is not overwritten
    assert main(["eval", str(run), "--speech", "--max-frames", "2", "--no-progress"]) == 0
    own = json.loads((run / "eval" / "speech" / "metrics.json").read_text())
    # the voice and the baselines that hear the sound (linear, nearest) all hear it by the chosen loudness
    assert report["lip_vertex_error"] != own["lip_vertex_error"]
    for baseline in ("linear", "nearest"):
        assert report["baselines"][baseline]["lip_vertex_error"] != own["baselines"][baseline]["lip_vertex_error"]
    assert report["baselines"]["mean_face"]["lip_vertex_error"] == own["baselines"]["mean_face"]["lip_vertex_error"]
    assert main(["eval", str(run), "--loudness", "video"]) == 2
    assert capsys.readouterr().err.strip().endswith("--loudness goes with --speech")
