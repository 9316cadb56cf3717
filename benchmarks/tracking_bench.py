"""Photometric tracking against the truth on generated subjects: `geoavatar track` on `geoavatar synth` output.

    .venv/bin/python benchmarks/tracking_bench.py --work /work/track_runs/bench --subjects 0 --frames 48 --size 256 \
        [--epochs 8 6] [--sizes 64 128] [--per-face 1] [--threads 1] [--tracked NAME] [--set lr_translation=0.003 ...]

For each subject: generate (or reuse) WORK/synth<k>, run `geoavatar track` into WORK/tracked<k>, then compare the
written parameters (flame_param/ of the synthetic dataset: truth + tracker-like error) and the fitted ones
with the truth (flame_param_gt/), per split (train / test frames of the dataset): head rotation error (deg),
skull orientation error (deg: head and neck rotation together), translation error (mm), jaw error (deg), mean
posed-vertex error over the face region and over the lips (mm).
Prints a Markdown table and writes WORK/tracking_bench.json (WORK/tracking_bench_NAME.json with --tracked NAME).

With --prepare the subject's frames also go through `geoavatar prepare` as a video (WORK/synth<k>.mp4 ->
WORK/prep<k>_landmarks with --no-photometric, then WORK/prep<k> with the photometric stage added by resuming a copy):
the landmark-only and the photometric fit of the whole preprocessing, from the pixels alone. prepare estimates its
own camera, focal length and identity, so these rows compare in each fit's own camera frame: the posed vertices
and the head's origin mapped by the frame's world-to-camera transform, the rotation as the camera-space head
rotation (vertex distances of the other rows are the same in either frame: the dataset's camera is rigid).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

FRAME_KEYS = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
COLUMNS = ("rotation_deg", "skull_deg", "translation_mm", "jaw_deg", "face_mm", "lips_mm", "face_aligned_mm", "lips_aligned_mm")


def load_params(root: Path, folder: str, timesteps) -> dict[str, torch.Tensor]:
    arrays = [dict(np.load(root / folder / f"{t:05d}.npz")) for t in timesteps]
    out = {k: torch.as_tensor(np.concatenate([a[k] for a in arrays])).float() for k in FRAME_KEYS}
    out["shape"] = torch.as_tensor(arrays[0]["shape"]).float()
    if "static_offset" in arrays[0]:
        out["static_offset"] = torch.as_tensor(arrays[0]["static_offset"]).float()
    return out


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    """Angle of R(a)^T R(b) per row, degrees (axis-angle inputs [T, 3])."""
    from scipy.spatial.transform import Rotation

    relative = Rotation.from_rotvec(a.numpy().astype(np.float64)).inv() * Rotation.from_rotvec(b.numpy().astype(np.float64))
    return np.degrees(relative.magnitude())


def errors(head, params: dict, truth: dict) -> dict[str, np.ndarray]:
    """Per-frame errors of `params` against `truth`."""
    with torch.no_grad():
        a, b = head.forward_params(params).vertices, head.forward_params(truth).vertices  # [T, V, 3]
    return {
        "rotation_deg": angle_deg(params["rotation"], truth["rotation"]),
        "skull_deg": skull_orientation_error(head, params, a, truth, b),
        "translation_mm": (params["translation"] - truth["translation"]).norm(dim=-1).numpy() * 1000,
        "jaw_deg": angle_deg(params["jaw_pose"], truth["jaw_pose"]),
        **vertex_errors(head, a, b),
    }


def skull_orientation_error(head, params: dict, a: torch.Tensor, truth: dict, b: torch.Tensor) -> np.ndarray:
    """[T] degrees between the skull's orientations of the posed vertices a and b [T, V, 3] (in one frame of axes):
    the rotation from each identity's rest skull to its posed skull (head.view_angles), so the head's and the neck's
    rotation count together, however a fit splits them."""
    from scipy.spatial.transform import Rotation

    from geoavatar.head.view_angles import face_rotation, rest_skull
    from geoavatar.head.params import HeadParams
    from geoavatar.head.regions import skull_vertex_ids

    ids = skull_vertex_ids(head)
    rotations = [face_rotation(rest_skull(head, HeadParams.from_npz(p)), x[:, ids]) for p, x in ((params, a), (truth, b))]
    return np.degrees(Rotation.from_matrix((rotations[0].transpose(1, 2) @ rotations[1]).numpy()).magnitude())


def vertex_errors(head, a: torch.Tensor, b: torch.Tensor) -> dict[str, np.ndarray]:
    """Per-frame mean face / lips distance (mm) of posed vertices a to b [T, V, 3], as they are and after the one
    similarity transform (scale, rotation, translation) that best maps all of a's face onto b's over the video:
    what is left when the video-wide offset and a monocular fit's focal / depth scale are forgiven."""
    face, lips = (torch.as_tensor(np.asarray(head.regions[name])) for name in ("face", "lips"))
    aligned = _video_similarity(a[:, face].reshape(-1, 3).double(), b[:, face].reshape(-1, 3).double())(a.double())
    out = {}
    for suffix, points in (("", a.double()), ("_aligned", aligned)):
        distance = (points - b.double()).norm(dim=-1) * 1000  # [T, V] mm
        out[f"face{suffix}_mm"] = distance[:, face].mean(1).numpy()
        out[f"lips{suffix}_mm"] = distance[:, lips].mean(1).numpy()
    return out


def _video_similarity(x: torch.Tensor, y: torch.Tensor):
    """The least-squares similarity y ~ s R x + t (Umeyama) of points x, y [N, 3], as a function of points [..., 3]."""
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    u, sigma, vt = torch.linalg.svd(yc.T @ xc / len(x))
    d = torch.ones(3, dtype=x.dtype)
    d[2] = torch.sign(torch.det(u @ vt))
    rotation = u @ torch.diag(d) @ vt
    scale = (sigma * d).sum() / xc.square().sum(1).mean()
    return lambda points: scale * points @ rotation.T + (my - scale * rotation @ mx)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--subjects", type=int, nargs="+", default=[0])
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--epochs", type=int, nargs="+", default=None, help="passed to geoavatar track --epochs")
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="passed to geoavatar track --sizes")
    parser.add_argument("--per-face", type=int, default=None, help="passed to geoavatar track --per-face")
    parser.add_argument("--threads", type=int, default=None, help="passed to geoavatar track --threads")
    parser.add_argument("--prepare", action="store_true", help="also the landmark-only and photometric fits of "
                        "`geoavatar prepare` on the frames as a video (camera frame; see the module docstring)")
    parser.add_argument("--tracked", default="tracked", help="name of the output folder in WORK (tracked<k>)")
    parser.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE",
                        help="PhotometricConfig fields (Python literals), e.g. pose_smooth_weight=30 epochs='(16, 12)': "
                             "the fit runs through this script (track_subject, one thread) instead of `geoavatar track`")
    args = parser.parse_args()
    if args.set and (args.epochs or args.sizes or args.per_face or args.threads):
        parser.error("--set replaces the track options: give epochs / sizes / per_face as --set fields")
    from geoavatar.data.dataset import open_subject
    from geoavatar.head import load_head_model

    head = load_head_model("openhead", mouth="geoavatar")
    geoavatar = [sys.executable, "-m", "geoavatar.cli"]
    results, rows = {}, []
    for subject in args.subjects:
        synth, tracked = args.work / f"synth{subject}", args.work / f"{args.tracked}{subject}"
        if not (synth / "flame_param_gt").is_dir():
            subprocess.run([*geoavatar, "synth", "--out", str(synth), "--subject", str(subject), "--frames",
                            str(args.frames), "--size", str(args.size), "--no-progress"], check=True)
        command = [*geoavatar, "track", str(synth), "--out", str(tracked), "--overwrite", "--no-progress"]
        if args.set:
            command = [sys.executable, __file__, "--fit-with", str(synth), str(tracked), *args.set]
        if args.epochs:
            command += ["--epochs", *map(str, args.epochs)]
        if args.sizes:
            command += ["--sizes", *map(str, args.sizes)]
        if args.per_face:
            command += ["--per-face", str(args.per_face)]
        if args.threads:
            command += ["--threads", str(args.threads)]
        started, cpu, load = time.perf_counter(), _children_cpu(), os.getloadavg()[0]
        subprocess.run(command, check=True)
        seconds, cpu = time.perf_counter() - started, _children_cpu() - cpu
        source = open_subject(synth)
        split = source.split()
        truth = load_params(synth, "flame_param_gt", source.timesteps)
        written = load_params(synth, "flame_param", source.timesteps)
        fitted = load_params(tracked, "flame_param", source.timesteps)
        row_of = {t: i for i, t in enumerate(source.timesteps)}
        measured = {"written": errors(head, written, truth), "photometric": errors(head, fitted, truth)}
        if args.prepare:
            measured.update(prepare_errors(head, args.work, subject, synth, truth, source, geoavatar))
        results[subject] = {"seconds": seconds, "cpu_seconds": cpu, "frames": len(source.timesteps),
                            "load_average_1min_before_after": [load, os.getloadavg()[0]], "command": command[2:]}
        for name, timesteps in (("train", split.train), ("test", split.test)):
            ids = [row_of[t] for t in timesteps]
            for kind, values in measured.items():
                summary = {k: float(v[ids].mean()) for k, v in values.items()}
                results[subject][f"{name}/{kind}"] = summary
                rows.append(f"| {subject} | {name} ({len(ids)}) | {kind} | " + " | ".join(
                    f"{summary[k]:.2f}" for k in COLUMNS) + " |")
    print("| subject | frames | parameters | rotation (deg) | skull orientation (deg) | translation (mm) | jaw (deg) "
          "| face (mm) | lips (mm) | face, video-wide similarity removed (mm) | lips, the same (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    for subject, result in results.items():
        before, after = result["load_average_1min_before_after"]
        print(f"subject {subject}: geoavatar track took {result['seconds']:.1f} s wall, {result['cpu_seconds']:.1f} s CPU "
              f"(user + sys) for {result['frames']} frames (load average {before:.1f} before, {after:.1f} after)")
    name = "tracking_bench.json" if args.tracked == "tracked" else f"tracking_bench_{args.tracked}.json"
    (args.work / name).write_text(json.dumps(results, indent=2) + "\n")
    return 0


def prepare_errors(head, work: Path, subject: int, synth: Path, truth: dict, source, geoavatar: list[str]) -> dict:
    """Errors of `geoavatar prepare`'s landmark-only and photometric fits of the subject's frames, in camera frames."""
    import shutil

    from PIL import Image

    from geoavatar.data.dataset import open_subject
    from geoavatar.io.video import write_mp4

    video = work / f"synth{subject}.mp4"
    if not video.is_file():
        frames = sorted(source.frames, key=lambda f: f.row)
        write_mp4(video, (np.asarray(Image.open(f.image_path).convert("RGB")) for f in frames), fps=25.0, crf=12)
    landmarks, photometric = work / f"prep{subject}_landmarks", work / f"prep{subject}"
    size = str(max(source.frames[0].width, source.frames[0].height))
    if not (landmarks / "dataset").is_dir():
        subprocess.run([*geoavatar, "prepare", str(video), "--out", str(landmarks), "--size", size, "--no-photometric",
                        "--no-progress"], check=True)
    if not (photometric / "dataset").is_dir():
        shutil.copytree(landmarks, photometric)
        subprocess.run([*geoavatar, "prepare", str(video), "--out", str(photometric), "--size", size, "--no-progress"],
                       check=True)
    truth_view = _viewmats(source)
    out = {}
    for name, folder in (("landmarks (prepare --no-photometric)", landmarks), ("photometric (prepare)", photometric)):
        fitted_subject = open_subject(folder / "dataset")
        if len(fitted_subject.timesteps) != len(source.timesteps):
            raise SystemExit(f"{folder}: {len(fitted_subject.timesteps)} frames, the subject has {len(source.timesteps)}")
        fitted = load_params(folder / "dataset", "flame_param", fitted_subject.timesteps)
        out[name] = camera_errors(head, fitted, _viewmats(fitted_subject), truth, truth_view)
    return out


def _viewmats(subject) -> torch.Tensor:
    """[T, 4, 4] world-to-camera per row of a monocular subject."""
    frames = sorted(subject.frames, key=lambda f: f.row)
    return torch.as_tensor(np.stack([f.viewmat for f in frames])).float()


def camera_errors(head, params: dict, view: torch.Tensor, truth: dict, truth_view: torch.Tensor) -> dict[str, np.ndarray]:
    """errors() with each fit in its own camera frame: params / view [T, 4, 4] against truth / truth_view."""
    from scipy.spatial.transform import Rotation

    def in_camera(p, v):
        with torch.no_grad():
            vertices = head.forward_params(p).vertices  # [T, V, 3]
        points = vertices @ v[:, :3, :3].transpose(1, 2) + v[:, None, :3, 3]
        origin = (v[:, :3, :3] @ p["translation"][..., None])[..., 0] + v[:, :3, 3]  # [T, 3]
        rotation = Rotation.from_matrix(v[:, :3, :3].double().numpy()) * Rotation.from_rotvec(p["rotation"].double().numpy())
        return points, origin, torch.as_tensor(rotation.as_rotvec()).float()

    a, origin_a, rot_a = in_camera(params, view)
    b, origin_b, rot_b = in_camera(truth, truth_view)
    return {"rotation_deg": angle_deg(rot_a, rot_b), "skull_deg": skull_orientation_error(head, params, a, truth, b),
            "translation_mm": (origin_a - origin_b).norm(dim=-1).numpy() * 1000,
            "jaw_deg": angle_deg(params["jaw_pose"], truth["jaw_pose"]), **vertex_errors(head, a, b)}


def fit_with(synth: Path, tracked: Path, settings: list[str]) -> None:
    """`geoavatar track synth --out tracked --overwrite` with PhotometricConfig fields set from FIELD=VALUE strings."""
    import ast
    import shutil
    from dataclasses import replace

    from geoavatar.apps.track import track_subject, write_tracked_copy
    from geoavatar.data.dataset import open_subject
    from geoavatar.prep.photometric import PhotometricConfig
    from geoavatar.runtime import num_threads, setup_process

    setup_process()
    changes = {}
    for item in settings:
        key, _, value = item.partition("=")
        changes[key] = ast.literal_eval(value)
    config = replace(PhotometricConfig(), **changes)
    subject = open_subject(synth)
    with num_threads(1):
        result = track_subject(subject, config, progress=False)
    shutil.rmtree(tracked, ignore_errors=True)
    write_tracked_copy(subject, result.params, tracked, {"set": changes, "log": result.log})


def _children_cpu() -> float:
    """User + system CPU seconds of the finished child processes."""
    times = os.times()
    return times.children_user + times.children_system


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--fit-with":
        fit_with(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4:])
        sys.exit(0)
    sys.exit(main())
