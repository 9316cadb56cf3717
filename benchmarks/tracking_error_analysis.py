"""What the written parameters' error of a generated subject consists of, and how the tracker's cues respond to depth.

    .venv/bin/python benchmarks/tracking_error_analysis.py --data D [--landmarks]

D: `geoavatar synth` output (flame_param/ = truth + tracker-like error, flame_param_gt/ = truth). Prints:

1. Decomposition, per split: the mean posed-vertex error over the face and the lips (mm) of the written
   parameters; with one parameter group replaced by the truth; with only that group wrong; and the rigid error
   split into its part shared by the whole video (one world rotation and one translation, their means) and the rest.
   The shared part is what a fit that only makes the frames agree with each other (a free albedo) cannot see.
2. Depth response of fit_photometric's image term: frames rendered with the fit's own appearance model (a patterned
   albedo on the head, tests/test_photometric.py), the term with that exact albedo at each pyramid level (coarse
   levels rendered at their own size, and at the finest size area-downsampled: PhotometricConfig.supersample), at
   the truth moved along the optical axis: where its minimum lies.
3. With --landmarks: the same response of prep.tracking's landmark term on D, with MediaPipe landmarks detected on
   D's frames, at the truth and at the written parameters.
4. With --fitted F (a `geoavatar track` copy of D): what the fit's remaining error consists of, per split: the face
   error after removing each frame's best translation, then its best rigid motion (Procrustes); the face centroid's
   error in the camera's axes (mean |.|, std, lag-1 autocorrelation over frames: a slow drift or a jitter); and the
   face error after a Gaussian temporal filter of the fitted translation alone and of the whole head pose.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from tracking_bench import FRAME_KEYS, load_params  # noqa: E402

DEPTHS_MM = (-20, -10, -5, -2, 0, 2, 5, 10, 20)


def vertex_error(head, params: dict, truth_vertices: torch.Tensor, rows: list[int]) -> tuple[float, float]:
    """Mean face and lips posed-vertex error (mm) of `params` on `rows`."""
    with torch.no_grad():
        vertices = head.forward_params(params).vertices
    distance = (vertices - truth_vertices).norm(dim=-1)[rows] * 1000  # [R, V]
    return tuple(float(distance[:, torch.as_tensor(np.asarray(head.regions[n]))].mean()) for n in ("face", "lips"))


def shared_rigid_offset(written: dict, truth: dict) -> dict:
    """The truth moved by the written error's video-wide part: mean world rotation error, mean translation error."""
    error = Rotation.from_rotvec(written["rotation"].double().numpy()) * Rotation.from_rotvec(truth["rotation"].double().numpy()).inv()
    mean = Rotation.from_rotvec(error.as_rotvec().mean(0))
    out = dict(truth)
    out["rotation"] = torch.as_tensor((mean * Rotation.from_rotvec(truth["rotation"].double().numpy())).as_rotvec()).float()
    out["translation"] = truth["translation"] + (written["translation"] - truth["translation"]).mean(0)
    return out


def decomposition(head, data: Path) -> list[str]:
    from geoavatar.data.dataset import open_subject

    subject = open_subject(data)
    truth = load_params(data, "flame_param_gt", subject.timesteps)
    written = load_params(data, "flame_param", subject.timesteps)
    with torch.no_grad():
        truth_vertices = head.forward_params(truth).vertices
    split = subject.split()
    row_of = {t: i for i, t in enumerate(subject.timesteps)}
    splits = {"train": [row_of[t] for t in split.train], "test": [row_of[t] for t in split.test],
              "all": list(range(len(subject.timesteps)))}
    cases = {"written": written}
    for key in (*FRAME_KEYS, "shape"):
        cases[f"written, true {key}"] = {**written, key: truth[key]}
    for key in ("translation", "rotation", "expr", "jaw_pose", "neck_pose"):
        cases[f"truth, written {key} only"] = {**truth, key: written[key]}
    depth = truth["translation"].clone()
    depth[:, 2] += (written["translation"] - truth["translation"])[:, 2].mean()
    cases["truth + the video-wide depth error only"] = {**truth, "translation": depth}
    cases["truth + the video-wide rigid error only"] = shared_rigid_offset(written, truth)
    lines = ["| parameters | " + " | ".join(f"{s} face / lips (mm)" for s in splits) + " |",
             "|---|" + "---|" * len(splits)]
    for name, params in cases.items():
        cells = [vertex_error(head, params, truth_vertices, rows) for rows in splits.values()]
        lines.append(f"| {name} | " + " | ".join(f"{f:.2f} / {l:.2f}" for f, l in cells) + " |")
    d = (written["translation"] - truth["translation"]) * 1000
    lines.append("")
    lines.append("written translation error (mm), mean over frames x / y / z: " + " / ".join(f"{v:.2f}" for v in d.mean(0))
                 + "; std: " + " / ".join(f"{v:.2f}" for v in d.std(0)))
    return lines


def photometric_depth_response(head, frames: int = 3) -> list[str]:
    """fit_photometric's image term with the exact albedo, at the truth moved along the optical axis."""
    from test_photometric import PATTERN_SIZE, _render_frames, _truth, depth_response

    truth = _truth(head, frames)
    targets = _render_frames(head, truth, PATTERN_SIZE)
    lines = ["| level | " + " | ".join(f"{d:+d} mm" for d in DEPTHS_MM) + " |", "|---|" + "---|" * len(DEPTHS_MM)]
    for size, supersample in ((32, False), (64, False), (32, True), (64, True), (PATTERN_SIZE, True)):
        losses = depth_response(head, truth, targets, size, [1e-3 * d for d in DEPTHS_MM], supersample)
        best = int(np.argmin(losses))
        how = "" if size == PATTERN_SIZE else (", rendered at 128 px" if supersample else ", rendered at its size")
        lines.append(f"| {size} px{how} | " + " | ".join(("**%.4f**" if i == best else "%.4f") % v for i, v in enumerate(losses)) + " |")
    return lines


def landmark_depth_response(head, data: Path) -> list[str]:
    from geoavatar.apps.track import load_inputs
    from geoavatar.data.dataset import open_subject
    from geoavatar.head.params import HeadParams
    from geoavatar.prep.landmarks import FaceMesh, filter_landmarks, landmark_confidence
    from geoavatar.prep.tracking import GROUP_OF, GROUP_WEIGHTS, TrackingConfig, _data_term

    subject = open_subject(data)
    inputs = load_inputs(subject)
    raw, found = np.zeros((len(inputs.images), 478, 3)), np.zeros(len(inputs.images), bool)
    with FaceMesh() as mesh:
        for t, image in enumerate(inputs.images):
            points = mesh(np.ascontiguousarray(image))
            if points is not None:
                raw[t], found[t] = points, True
    filtered = filter_landmarks(raw, float(json.loads((data / "synth.json").read_text())["fps"]))
    confidence = torch.as_tensor(landmark_confidence(raw, filtered, found.astype(float))).float().clamp(0.05, 1.0)
    ids = head.landmark_ids.cpu().numpy()
    points = torch.as_tensor(filtered[:, ids, :2]).float()
    size = torch.as_tensor(np.linalg.norm(filtered[:, 10, :2] - filtered[:, 152, :2], axis=-1)).float().clamp_min(1.0)
    weights = torch.tensor([GROUP_WEIGHTS[GROUP_OF.get(int(i), "face_oval_lower")] for i in ids]).float()
    view, K = torch.as_tensor(inputs.viewmat).float(), torch.as_tensor(inputs.K).float()
    axis = view[:, 2, :3]
    lines = [f"MediaPipe found a face in {int(found.sum())} of {len(found)} frames", "",
             "| parameters | " + " | ".join(f"{d:+d} mm" for d in DEPTHS_MM) + " |", "|---|" + "---|" * len(DEPTHS_MM)]
    for name, folder in (("truth", "flame_param_gt"), ("written", "flame_param")):
        params = HeadParams.from_npz(load_params(data, folder, subject.timesteps))
        losses = []
        for d in DEPTHS_MM:
            moved = params.replace(translation=params.translation + 1e-3 * d * axis)
            with torch.no_grad():
                losses.append(float(_data_term(head, moved, view, K, points, size, weights, confidence, TrackingConfig().huber)))
        best = int(np.argmin(losses))
        lines.append(f"| {name} | " + " | ".join(("**%.3g**" if i == best else "%.3g") % v for i, v in enumerate(losses)) + " |")
    return lines


def _best_rigid(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """x [V, 3] moved by the rotation and translation that bring it closest to y [V, 3] (least squares)."""
    xc, yc = x - x.mean(0), y - y.mean(0)
    u, _, vt = torch.linalg.svd(xc.T @ yc)
    d = torch.ones(3, dtype=x.dtype)
    d[2] = torch.sign(torch.det(u @ vt))
    return xc @ (u @ torch.diag(d) @ vt) + y.mean(0)


def fitted_anatomy(head, data: Path, fitted: Path) -> list[str]:
    from scipy.ndimage import gaussian_filter1d

    from geoavatar.data.dataset import open_subject

    subject = open_subject(data)
    split, ts = subject.split(), subject.timesteps
    truth = load_params(data, "flame_param_gt", ts)
    fit = load_params(fitted, "flame_param", ts)
    face = torch.as_tensor(np.asarray(head.regions["face"]))
    with torch.no_grad():
        a = head.forward_params(fit).vertices[:, face].double()  # [T, F, 3]
        b = head.forward_params(truth).vertices[:, face].double()
    raw = (a - b).norm(dim=-1).mean(1) * 1000  # [T] mm
    moved = (a - a.mean(1, keepdim=True) + b.mean(1, keepdim=True) - b).norm(dim=-1).mean(1) * 1000
    rigid = torch.stack([(_best_rigid(a[i], b[i]) - b[i]).norm(dim=-1).mean() * 1000 for i in range(len(ts))])
    camera_axes = _camera_axes(data)  # [3, 3] columns: the camera's x, y, z in world axes
    centroid = ((a.mean(1) - b.mean(1)).numpy() * 1000) @ camera_axes  # [T, 3] mm, camera axes
    row = {t: i for i, t in enumerate(ts)}
    lines = ["| split | face (mm) | lips (mm) | after each frame's best translation | after its best rigid motion |",
             "|---|---:|---:|---:|---:|"]
    truth_vertices = head.forward_params(truth).vertices
    for name, timesteps in (("train", split.train), ("test", split.test)):
        ids = [row[t] for t in timesteps]
        lips = vertex_error(head, fit, truth_vertices, ids)[1]
        lines.append(f"| {name} | {raw[ids].mean():.2f} | {lips:.2f} | {moved[ids].mean():.2f} | {rigid[ids].mean():.2f} |")
    lines += ["", "| face centroid error, camera axis | mean abs (mm) | std (mm) | lag-1 autocorrelation |", "|---|---:|---:|---:|"]
    for k, axis in enumerate("xyz"):
        e = centroid[:, k] - centroid[:, k].mean()
        lines.append(f"| {axis} | {np.abs(centroid[:, k]).mean():.2f} | {e.std():.2f} | {(e[1:] * e[:-1]).mean() / e.var():.2f} |")
    lines += ["", "| temporal filter (Gaussian, sigma in frames) | train face (mm) | test face (mm) |", "|---|---:|---:|"]
    train_ids, test_ids = [row[t] for t in split.train], [row[t] for t in split.test]
    for keys, label in ((("translation",), "translation"), (("translation", "rotation", "neck_pose"), "head pose")):
        for sigma in (1.0, 2.0, 3.0):
            smoothed = dict(fit)
            for key in keys:
                smoothed[key] = torch.as_tensor(gaussian_filter1d(fit[key].double().numpy(), sigma, axis=0, mode="nearest")).float()
            train_face, _ = vertex_error(head, smoothed, head.forward_params(truth).vertices, train_ids)
            test_face, _ = vertex_error(head, smoothed, head.forward_params(truth).vertices, test_ids)
            lines.append(f"| {label}, sigma {sigma:g} | {train_face:.2f} | {test_face:.2f} |")
    return lines


def _camera_axes(data: Path) -> np.ndarray:
    """[3, 3] the first frame's camera axes (columns) in world axes, from transforms.json (camera-to-world)."""
    frames = json.loads((data / "transforms.json").read_text())["frames"]
    return np.asarray(frames[0]["transform_matrix"], dtype=np.float64)[:3, :3]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a `geoavatar synth` dataset")
    parser.add_argument("--landmarks", action="store_true", help="also the landmark term's depth response (MediaPipe)")
    parser.add_argument("--fitted", type=Path, help="a `geoavatar track` copy of D: only what its remaining error consists of")
    args = parser.parse_args()
    from geoavatar.head import load_head_model

    torch.set_num_threads(1)
    head = load_head_model("openhead", mouth="geoavatar")
    if args.fitted is not None:
        print("\n".join(fitted_anatomy(head, args.data, args.fitted)))
        return 0
    print("\n".join(decomposition(head, args.data)))
    print("\nphotometric image term (exact albedo) at the truth moved along the optical axis (+: away from the camera)\n")
    print("\n".join(photometric_depth_response(head)))
    if args.landmarks:
        print("\nlandmark term at the parameters moved along the optical axis\n")
        print("\n".join(landmark_depth_response(head, args.data)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
