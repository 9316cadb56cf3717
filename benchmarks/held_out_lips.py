"""How the held-out frames' mouths agree with MediaPipe's lips in the images: the tracker's rows (the dataset's)
against train's fit against the avatar (RUN/held_out.npz), and how far the fit moved each key from the tracker's
rows along the fit's blocks of 16 frames (the carry's drift).

    .venv/bin/python benchmarks/held_out_lips.py RUN PREPARED        # PREPARED: the folder `geoavatar prepare` wrote

MediaPipe's landmarks are prepare's (PREPARED/.prepare/landmarks.npz, in the dataset's image pixels). Per held-out
frame: the mean 2D distance of the head model's embedded lip landmarks from MediaPipe's, and the opening between the
inner lips' midpoints (MediaPipe 13 and 14), both in face widths (cheek to cheek, 234-454). Neither fit minimises the
opening directly: the tracker fits every landmark, the avatar fit the picture alone.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

INNER_UPPER, INNER_LOWER = 13, 14
LIPS = (61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291, 78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308, 185, 40,
        39, 37, 0, 267, 269, 270, 409, 191, 80, 81, 82, 13, 312, 311, 310, 415)  # MediaPipe's lip contours


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("prepared", type=Path)
    args = parser.parse_args()

    from geoavatar.head.params import FRAME_KEYS, HeadParams
    from geoavatar.render.camera import project
    from geoavatar.train.checkpoint import load_run, open_run_dataset
    from geoavatar.train.held_out_fit import BLOCK, read_held_out

    run = load_run(args.run, "cpu")
    test = open_run_dataset(run, "test")
    detected_all = np.load(args.prepared / ".prepare" / "landmarks.npz")["filtered"]  # [T, 478, >=2] per timestep
    held_out = read_held_out(args.run, run.info.step)
    if held_out is None:
        raise SystemExit(f"{args.run}: no held-out fit for its checkpoint")
    timesteps, fitted, scored = held_out.timesteps, held_out.rows, set(held_out.scored)
    fit_row = {t: i for i, t in enumerate(timesteps)}
    ids = run.head.landmark_ids.cpu().numpy()  # [L] MediaPipe ids of the model's landmarks
    position = {int(m): i for i, m in enumerate(ids)}
    lips = [position[m] for m in LIPS if m in position]
    scores: dict[str, list] = {"tracker": [], "fit": []}
    openings: dict[str, list] = {"mediapipe": [], "tracker": [], "fit": []}
    for frame in (frame for frame in test.frames if frame.timestep in scored):  # not the rows filled between
        detected = detected_all[frame.timestep][:, :2]  # [478, 2]
        width = float(np.linalg.norm(detected[234] - detected[454]))
        openings["mediapipe"].append(np.linalg.norm(detected[INNER_UPPER] - detected[INNER_LOWER]) / width)
        tracker = test.subject.frame_params(frame.row)
        fit = {**tracker, **{k: torch.as_tensor(fitted[k][fit_row[frame.timestep]])[None] for k in FRAME_KEYS}}
        for name, params in (("tracker", tracker), ("fit", fit)):
            with torch.no_grad():
                posed = run.head.forward_params(HeadParams.from_npz({k: torch.as_tensor(v).float()
                                                                      for k, v in params.items()}),
                                                vertex_ids=run.head.landmark_vertex_ids).landmarks  # [1, L, 3]
                pixels = project(posed, torch.from_numpy(frame.viewmat).float()[None],
                                 torch.from_numpy(frame.K).float()[None])[0][0].numpy()  # [L, 2]
            scores[name].append(np.linalg.norm(pixels[lips] - detected[ids[lips]], axis=-1).mean() / width)
            openings[name].append(np.linalg.norm(pixels[position[INNER_UPPER]] - pixels[position[INNER_LOWER]]) / width)
    report = {"frames": len(openings["fit"])}
    mediapipe = np.asarray(openings["mediapipe"])
    for name in ("tracker", "fit"):
        opening = np.asarray(openings[name])
        report[name] = {"lip_landmark_error": round(float(np.mean(scores[name])), 5),
                        "opening_r": round(float(np.corrcoef(mediapipe, opening)[0, 1]), 3),
                        "opening_bias": round(float((opening - mediapipe).mean()), 5),
                        "opening_mean_error": round(float(np.abs(opening - mediapipe).mean()), 5)}
    rows = {t: i for i, t in enumerate(test.subject.timesteps)}
    picked = [i for i, t in enumerate(timesteps) if t in scored]  # the fitted rows, in the blocks' order
    position_in_block = np.arange(len(picked)) % BLOCK < BLOCK // 2
    for key in ("expr", "jaw_pose", "rotation", "translation"):
        tracked = test.subject.params[key][[rows[timesteps[i]] for i in picked]].numpy().reshape(len(picked), -1)
        moved = np.linalg.norm(fitted[key][picked].reshape(len(picked), -1)[:, :tracked.shape[1]] - tracked, axis=1)
        report[f"fit_moved_{key}"] = {"first_half_of_blocks": round(float(moved[position_in_block].mean()), 4),
                                      "second_half_of_blocks": round(float(moved[~position_in_block].mean()), 4)}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
