"""The voice model against known truth: a generated subject whose sound is a known function of its mouth
(`synth --sound`). It learns the mouth from the training frames' sound and predicts the held-out frames' (which it
never heard); with the sound shifted against the frames it cannot. Plus the live stream, the idle motion, the model's
file and the dataset's sound on a real talking video."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from geoavatar.data.splits import ShortVideoWarning

FRAMES, SIZE = 300, 32
STEPS = 250


@pytest.fixture(scope="module")
def talking(tmp_path_factory):
    """A generated subject with its voice and a run of its untrained state (the parameters are what matter here)."""
    from apps_fixtures import make_untrained_run

    from geoavatar.data.synth.generate import SynthConfig, generate_dataset

    root = tmp_path_factory.mktemp("voice")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        data = generate_dataset(root / "data", SynthConfig(frames=FRAMES, size=SIZE, sound=True, workers=1),
                                progress=False)
    return data, make_untrained_run(data, root / "run")


@pytest.fixture(scope="module")
def learned(talking):
    """The run and the voice model it learns with STEPS steps."""
    return _learn(talking[1])


def _ground_truth_jaw(data, timesteps) -> np.ndarray:
    return np.array([np.load(data / "flame_param_gt" / f"{t:05d}.npz")["jaw_pose"].reshape(-1)[0] for t in timesteps])


def _learn(run_dir, steps: int = STEPS, members: int = 1):
    """One network (the default ensemble of three learns the same, three times over: test_voice_model_file... checks
    an ensemble's file)."""
    from geoavatar.train.checkpoint import open_run
    from geoavatar.voice.config import VoiceConfig
    from geoavatar.voice.train import train_voice

    run = open_run(run_dir, "cpu")
    return run, train_voice(run, VoiceConfig(steps=steps, validate_every=50, members=members), log=lambda _: None)


def _held_out_jaw_r(run, voice, data) -> float:
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.eval.speech import pearson

    test = run.info.timesteps["test"]
    sound = read_dataset_sound(data)
    held = sound.sound.segment(sound.frame_times[test[0]] - 0.02, sound.sound.seconds)
    face = voice.predict(held, sound.times(test) - held.start)
    return pearson(face.jaw[:, 0], _ground_truth_jaw(data, test))


def test_the_voice_learns_a_mouth_it_can_hear(talking, learned, tmp_path):
    data, _ = talking
    run, voice = learned
    r = _held_out_jaw_r(run, voice, data)
    assert r > 0.8, r  # the held-out jaw follows the ground truth from sound alone

    shifted = tmp_path / "shifted"
    shutil.copytree(data, shifted)
    info = json.loads((shifted / "audio.json").read_text())
    info["frame_times"] = {t: s + 0.6 for t, s in info["frame_times"].items()}  # sound 0.6 s off its frames
    (shifted / "audio.json").write_text(json.dumps(info))
    from geoavatar.voice.config import VoiceConfig
    from geoavatar.voice.train import train_voice

    misaligned = train_voice(run, VoiceConfig(steps=STEPS, validate_every=50, members=1), data_root=shifted,
                             log=lambda _: None)
    r_shifted = _held_out_jaw_r(run, misaligned, data)
    assert r_shifted < r - 0.3, (r, r_shifted)


def test_voice_model_file_round_trips_without_pickle(talking, tmp_path):
    from geoavatar.voice.model import VOICE_DIR, VoiceModel, VoiceModelError

    data, run_dir = talking
    run, voice = _learn(run_dir, steps=10, members=2)  # an ensemble: both members saved and averaged
    with pytest.raises(VoiceModelError, match="has no voice model.*geoavatar voice"):
        VoiceModel.load(tmp_path)
    assert 1.0 <= voice.gain <= 2.0 and voice.info["gain"] == pytest.approx(voice.gain, abs=1e-4)
    voice.gain = 1.3  # the validation frames' gain travels with the file
    voice.save(tmp_path)
    with np.load(tmp_path / VOICE_DIR / "voice.npz", allow_pickle=False) as npz:  # plain arrays only
        assert all(npz[k].dtype != object for k in npz.files)
    back = VoiceModel.load(tmp_path)
    assert len(back.net.members) == 2 and back.gain == pytest.approx(1.3)
    assert np.array_equal(back.level_slope, voice.level_slope)  # [D] the mean face's slope with the speech level
    from dataclasses import replace

    from geoavatar.errors import GeoAvatarWarning

    with pytest.warns(GeoAvatarWarning, match="learned before the level slope"):  # a voice saved before it: said
        assert not replace(back, level_slope=None).hearing("video").follows_level
    from geoavatar.data.sound import read_dataset_sound

    sound = read_dataset_sound(data).sound.segment(0.0, 2.0)
    times = np.arange(50) / 25.0
    a, b = voice.predict(sound, times), back.predict(sound, times)
    assert np.allclose(a.expr, b.expr, atol=1e-6) and np.allclose(a.jaw, b.jaw, atol=1e-6)
    weights, info = tmp_path / VOICE_DIR / "voice.npz", tmp_path / VOICE_DIR / "voice.json"
    whole, described = weights.read_bytes(), info.read_text()
    with np.load(weights) as npz:
        slope = {k: npz[k] for k in npz.files} | {"level_slope": np.zeros(5)}
    # damaged files give one line, whatever the damage: bytes, a file cut short, a json list, an array's shape
    for damage in (lambda: weights.write_bytes(b"damaged"), lambda: weights.write_bytes(whole[:len(whole) // 2]),
                   lambda: info.write_text("[]"), lambda: np.savez(weights, **slope)):
        weights.write_bytes(whole), info.write_text(described)
        damage()
        with pytest.raises(VoiceModelError, match="cannot be read"):
            VoiceModel.load(tmp_path)
    assert not list((tmp_path / VOICE_DIR).glob(".*"))  # saving left no staged file behind


def test_the_live_stream_gives_the_files_faces(talking, learned):
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.voice.inputs import log_mel_torch, speech_stats
    from geoavatar.voice.stream import VoiceStream
    from geoavatar.sound.features import power_frames

    data, _ = talking
    _, voice = learned
    sound = read_dataset_sound(data).sound.segment(0.0, 3.0)
    stats = speech_stats(log_mel_torch(torch.from_numpy(power_frames(sound))))
    stream = VoiceStream(voice, 25.0, stats=stats)
    frames, rng, at = [], np.random.default_rng(1), 0
    while at < len(sound.samples):
        size = int(rng.integers(100, 900))
        frames += stream.push(sound.samples[at:at + size])
        at += size
    assert [k for k, _, _ in frames] == list(range(len(frames)))
    assert len(frames) >= 3.0 * 25 - 4  # all but the last look-ahead
    for k, _, heard in frames:  # a frame is made once its instant and the look-ahead have been heard
        assert heard >= k / 25.0 + voice.config.ahead - 0.011
    frames += stream.finish(len(sound.samples))  # the sound ended: the frames within its look-ahead of the end
    assert [k for k, _, _ in frames] == list(range(75)) and stream.finish(len(sound.samples)) == []  # as a file's
    offline = voice.predict(sound, np.arange(len(frames)) / 25.0, stats)
    live_jaw = np.concatenate([face.jaw for _, face, _ in frames])
    assert np.abs(live_jaw - offline.jaw).max() < 1e-5
    short = VoiceStream(voice, 25.0, stats=stats)  # a sound shorter than the look-ahead still gives its frames
    assert len(short.push(sound.samples[:800]) + short.finish(800)) == 2


def test_the_level_slope_is_how_the_mean_face_follows_the_speech_level():
    """Stretches of sound at known levels whose frames' faces move with the level by a known slope (plus noise that
    averages out over a stretch): level_slope finds that slope; too little sound gives none."""
    from geoavatar.sound import FRAME_RATE
    from geoavatar.voice.train import LEVEL_STRETCH, level_slope

    rng = np.random.default_rng(0)
    chunk = int(LEVEL_STRETCH * FRAME_RATE) // 2  # the slope's stretches start every half stretch
    levels = rng.uniform(-0.3, 0.3, 12)  # [12] log10 units: one level per half stretch, 30 s in all
    mel = torch.from_numpy(np.repeat(levels, chunk)[:, None] + rng.normal(0, 0.05, (12 * chunk, 40))).float()
    centres = torch.arange(0, 12 * chunk, 4)  # a video frame every 40 ms
    truth = np.array([0.8, -0.5, 0.0])  # [D] the face's change per log10 unit
    faces = levels[(centres // chunk).numpy()][:, None] * truth + rng.normal(0, 0.05, (len(centres), 3))
    slope = level_slope(mel, centres, torch.from_numpy(faces).float())
    assert np.allclose(slope, truth, atol=0.08), slope
    short = centres[centres < 2 * chunk]  # one stretch of sound: nothing to fit a slope on
    assert not level_slope(mel[:2 * chunk], short, torch.from_numpy(faces[:len(short)]).float()).any()


def test_the_videos_loudness_lets_a_softer_voice_move_the_mouth_less(talking, learned):
    """own (the default): a sound 12 dB softer gives the same faces, normalised by its own speech; video: by the
    training sound's, and the mean face follows the speech level, so the softer sound opens the mouth less; a live
    stream keeps those statistics and follows the level of what it has heard."""
    from dataclasses import replace

    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.sound.features import power_frames
    from geoavatar.sound.track import Sound
    from geoavatar.voice.inputs import log_mel_torch
    from geoavatar.voice.model import LEVEL_LIMIT
    from geoavatar.voice.stream import VoiceStream

    data, _ = talking
    _, voice = learned
    sound = read_dataset_sound(data).sound.segment(0.0, 6.0)
    softer = Sound(sound.samples / 4.0, sound.rate, sound.start)
    times = np.arange(140) / 25.0
    own, own_softer = voice.predict(sound, times), voice.predict(softer, times)
    assert np.abs(own.jaw - own_softer.jaw).max() < 1e-3
    assert voice.level_slope is not None and not voice.level_slope.any()  # 10 s of sound: too little for a slope
    sloped = replace(voice, level_slope=np.full(len(voice.target_mean), 0.1))  # a slope to follow: louder, wider
    video = sloped.hearing("video")
    assert voice.loudness == "own" and video.loudness == "video"  # a copy: the loaded voice is unchanged
    loud, soft = video.predict(sound, times), video.predict(softer, times)
    assert voice.level_of(log_mel_torch(torch.from_numpy(power_frames(softer)))) == 0.0  # own: no level
    level = video.level_of(log_mel_torch(torch.from_numpy(power_frames(softer))))
    assert level == -LEVEL_LIMIT  # 12 dB softer: beyond the 6 dB that the face follows
    flat = voice.predict(softer, times, voice.speech)  # the video's statistics, without the level
    assert np.allclose(soft.jaw - flat.jaw, level * 0.1, atol=1e-5)
    assert np.allclose(soft.expr[:, :voice.expr_dims] - flat.expr[:, :voice.expr_dims], level * 0.1, atol=1e-5)
    opened, softly = loud.jaw[:, 0], soft.jaw[:, 0]  # [140] the jaw's opening angle
    assert softly.mean() < opened.mean() - 0.2 * opened.std(), (softly.mean(), opened.mean())

    stream = VoiceStream(video, 25.0)
    live = []
    for at in range(0, len(softer.samples), 800):
        live += stream.push(softer.samples[at:at + 800])
    assert stream.fixed and stream.stats is voice.speech and stream.level == level
    live_jaw = np.concatenate([face.jaw for _, face, _ in live])[:len(times)]  # [140, 3]
    # once it has heard 2.5 s (LOUD_SECONDS of loud sound, then an update) the stream follows the clip's level
    assert len(live_jaw) == len(times) and np.abs(live_jaw[75:] - soft.jaw[75:]).max() < 1e-5
    with pytest.raises(ValueError, match="loudness must be one of own, video"):
        voice.hearing("loud")


def test_idle_motion_keeps_the_lips_still_and_plays_the_training_motion(learned):
    from geoavatar.voice.face import FaceProbe

    run, voice = learned
    idle = voice.idle
    player = idle.player(25.0, seed=3)
    frames = player.take(400)
    again = idle.player(25.0, seed=3).take(400)
    assert all(np.array_equal(frames[k], again[k]) for k in frames)  # seeded
    # the head moves as in training (not frozen), within the training range
    rotation = idle.sequences["rotation"]
    assert frames["rotation"].std(0).max() > 0.3 * rotation.std(0).max()
    assert (frames["rotation"] <= rotation.max(0) + 1e-6).all() and (frames["rotation"] >= rotation.min(0) - 1e-6).all()
    # the upper-face change moves the eyelids / brows much more than the lips
    from geoavatar.train.run_frames import RunFrames

    probe = FaceProbe(run.head, RunFrames(run).identity())
    upper = torch.as_tensor(frames["upper_expr"])
    zero = torch.zeros(len(upper), 3)
    base = torch.zeros_like(upper)
    lips = (probe.lips(upper, zero) - probe.lips(base, zero)).norm(dim=-1).mean()
    brows = (probe.upper(upper, zero) - probe.upper(base, zero)).norm(dim=-1).mean()
    assert brows > 5 * lips


def test_each_member_of_the_ensemble_holds_out_its_own_block():
    from types import SimpleNamespace

    from geoavatar.voice.config import VoiceConfig
    from geoavatar.voice.train import _Trainer, validation_blocks

    # three members: blocks of a tenth ending at a third, two thirds and the end; one member: the last tenth
    assert validation_blocks(100, VoiceConfig(members=3)) == [slice(23, 33), slice(57, 67), slice(90, 100)]
    assert validation_blocks(100, VoiceConfig(members=1)) == [slice(90, 100)]
    assert validation_blocks(100, VoiceConfig(members=2, validation=0.0)) == [slice(0, 100)] * 2

    # the loss never reaches a member's prediction of a frame in its own block (nor that frame's change)
    metric = torch.eye(4)
    learns = torch.ones(2, 3, 8, dtype=torch.bool)  # [K, R, L]
    learns[0, 1, 2:5] = False
    predicted = torch.randn(2, 3, 8, 4, requires_grad=True)  # [K, R, L, D]
    loss = _Trainer._loss(SimpleNamespace(metric=metric, config=VoiceConfig()), predicted, torch.zeros(3, 8, 4),
                          learns)
    loss.backward()
    grad = predicted.grad.abs().sum(-1)  # [K, R, L]
    assert torch.all(grad[0, 1, 2:5] == 0) and torch.all(grad[0, 1, :2] > 0) and torch.all(grad[1] > 0)


def test_a_dataset_without_speech_says_how_to_get_a_voice(tmp_path):
    from apps_fixtures import make_subject, make_untrained_run

    from geoavatar.train.checkpoint import open_run
    from geoavatar.voice.model import VoiceModelError
    from geoavatar.voice.train import train_voice

    data = make_subject(tmp_path / "quiet", frames=8)
    run = open_run(make_untrained_run(data, tmp_path / "run"), "cpu")
    with pytest.raises(VoiceModelError, match="no sound track.*talks"):
        train_voice(run)


def test_speech_scores_have_known_values_and_follow_a_copys_parameters(talking, learned, tmp_path):
    from geoavatar.eval.speech import best_lag, face_scores, speech_dir
    from geoavatar.eval.speech_run import evaluate_speech
    from geoavatar.train.checkpoint import RunError, open_run
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice.face import FaceProbe
    from geoavatar.voice.model import SpokenFace

    data, _ = talking
    run, voice = learned
    # a signal against itself 3 frames late (25 fps): +120 ms, and r 1 there
    signal = np.convolve(np.random.default_rng(0).normal(size=200), np.ones(5), "same")
    lag, r = best_lag(np.concatenate([np.zeros(3), signal[:-3]]), signal, 25.0)
    assert lag == pytest.approx(120.0) and r == pytest.approx(1.0)

    # the held-out faces against themselves score perfectly; with the jaw opened further the lips err
    frames = RunFrames(run)
    rows = [frames.row(t) for t in run.info.timesteps["test"]]
    tracked = SpokenFace.from_rows(frames.values.expr, frames.values.jaw_pose, rows)
    probe = FaceProbe(run.head, frames.identity())
    same = face_scores(probe, tracked, tracked, 25.0)
    assert same["lip_vertex_error"] == 0.0 and same["lag_ms"] == 0.0
    assert same["mouth_open_correlation"] == pytest.approx(1.0) and same["upper_face_dynamics"] == pytest.approx(0.0)
    opened = SpokenFace(tracked.expr, tracked.jaw + np.array([0.1, 0.0, 0.0], np.float32))
    assert face_scores(probe, opened, tracked, 25.0)["lip_vertex_error"] > 1e-6

    # the learned voice beats the mean face and hears the mouth on time
    scores = evaluate_speech(run, voice, render=False).scores
    assert scores["voice"]["mouth_open_correlation"] > 0.7 and abs(scores["voice"]["lag_ms"]) <= 40
    assert scores["voice"]["lip_vertex_error"] < scores["mean_face"]["lip_vertex_error"]
    # --data COPY: the copy's held-out parameters are the reference (here a closed jaw: the mean face wins)
    copy = tmp_path / "copy"
    shutil.copytree(data, copy)
    for timestep in run.info.timesteps["test"]:
        path = copy / "flame_param" / f"{timestep:05d}.npz"
        with np.load(path) as npz:
            arrays = {k: npz[k] for k in npz.files}
        arrays["jaw_pose"] = np.zeros_like(arrays["jaw_pose"])
        np.savez(path, **arrays)
    closed = evaluate_speech(run, voice, data=copy, render=False).scores
    assert closed["mean_face"]["lip_vertex_error"] < closed["voice"]["lip_vertex_error"]

    # the run's own dataset given again is no copy: the held-out fit's rows (here a jaw opened beyond the dataset's)
    # stay the reference, and each report has its own folder
    fitted = open_run(run.info.run_dir, "cpu")
    test = fitted.info.timesteps["test"]
    rows = [fitted.info.timesteps["all"].index(t) for t in test]
    fitted.info.frame_params["jaw_pose"][rows, 0] += 0.2
    fitted.info.held_out, fitted.info.held_out_scored = list(test), list(test)
    own = evaluate_speech(fitted, voice, render=False).scores
    assert own["voice"]["lip_vertex_error"] != scores["voice"]["lip_vertex_error"]
    assert evaluate_speech(fitted, voice, data=data, render=False).scores == own
    mixed = open_run(run.info.run_dir, "cpu")  # held-out frames among the training ones: their sound was heard
    mixed.info.timesteps["test"] = mixed.info.timesteps["train"][10:20]
    with pytest.raises(RunError, match="lie among its training frames"):
        evaluate_speech(mixed, voice, render=False)
    reports = Path("RUN") / "eval"
    assert speech_dir("RUN", "video", "copy") == reports / "speech@copy@video-loudness"
    assert speech_dir("RUN") == reports / "speech"


def test_a_resumed_finished_run_keeps_the_voice_learned_after_it(learned, tmp_path):
    """train --resume of a finished run learns the voice only when the run has none readable, or an older one than
    its avatar: a voice learned after it (`geoavatar voice RUN --steps ...`) is kept."""
    import os

    from geoavatar.apps.train import _voice_is_newer

    run, voice = learned
    copy = tmp_path / "run"
    shutil.copytree(run.info.run_dir, copy)
    final = shutil.copy(copy / "checkpoints" / "last.pt", copy / "checkpoints" / "final.pt")
    assert not _voice_is_newer(copy)  # no voice yet
    voice.save(copy)
    assert _voice_is_newer(copy)
    later = os.stat(copy / "voice" / "voice.json").st_mtime + 10
    os.utime(final, (later, later))  # the avatar trained again after the voice
    assert not _voice_is_newer(copy)
