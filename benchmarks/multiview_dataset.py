"""A copy of a generated subject's dataset whose TRAINING split also holds views from turned cameras (issue #18).

What a second camera would give a monocular avatar: every EVERY-th training frame is rendered again from the named
novel-view cameras (geoavatar synth's NOVEL_VIEWS: yaw+30, yaw-30, yaw+60, yaw-60, pitch+20, pitch-20, turned about
the frame's true head centre, room-fixed lights) and appended to transforms_train.json with the frame's parameters.
The test and novel splits are untouched, so `geoavatar eval RUN --split novel` stays held out. An upper reference
for what the monocular runs could reach at turned views, not a training mode.

usage: python benchmarks/multiview_dataset.py SRC DST [EVERY=3] [VIEWS=yaw+30,yaw-30]
    SRC: a dataset made by `geoavatar synth` (an exact-parameter copy of one: benchmarks/exact_params_dataset.py)
"""

import json
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image

import geoavatar.data.synth.generate as synth

src, dst = Path(sys.argv[1]), Path(sys.argv[2])
every = int(sys.argv[3]) if len(sys.argv) > 3 else 3
views = (sys.argv[4] if len(sys.argv) > 4 else "yaw+30,yaw-30").split(",")
if dst.exists():
    sys.exit(f"{dst} exists; choose a new folder")
meta = json.loads((src / "synth.json").read_text())
shutil.copytree(src, dst)
config = synth.SynthConfig(subject=meta["subject"]["index"], frames=meta["frames"], size=meta["size"],
                           seed=meta["seed"], fps=meta["fps"], fov_deg=meta["fov_deg_vertical"], ssaa=meta["ssaa"])
actor = synth.actor_for_subject(config.subject)
camera = synth.frontal_camera(actor, config.size, config.fov_deg)
renderer = synth.ActorRenderer(actor, camera, synth.get_subject(config.subject).background_rgb, ssaa=config.ssaa)
truth, _ = synth.motion_to_params(synth.script_motion(config.frames, config.seed, config.fps), actor)
chosen = [(index, yaw, pitch) for index, name, yaw, pitch in synth.NOVEL_VIEWS if name in views]
jobs = []
for t in range(0, meta["test_start"], every):
    centre = synth.skull_centre(synth._posed_vertices(actor, truth, t, t + 1)[0], actor.head)  # [3]
    jobs += [(t, index, synth.orbit_camera(camera, yaw, pitch, centre)) for index, yaw, pitch in chosen]
cameras = {(t, index): cam for t, index, cam in jobs}
train = json.loads((dst / "transforms_train.json").read_text())
template = train["frames"][0]
for t, index, image, mask in synth._render_frames(actor, renderer, truth, jobs, config.workers):
    name = f"{t:05d}_{index:02d}.png"
    Image.fromarray(image).save(dst / "images" / name)
    Image.fromarray(mask).save(dst / "fg_masks" / name)
    c2w = np.linalg.inv(np.asarray(cameras[(t, index)].viewmat, dtype=np.float64))
    c2w[:3, 1:3] *= -1  # OpenCV axes -> the layout's OpenGL axes (as transforms_novel.json)
    train["frames"].append(dict(template, timestep_index=t, camera_index=index, file_path=f"images/{name}",
                                fg_mask_path=f"fg_masks/{name}", flame_param_path=f"flame_param/{t:05d}.npz",
                                transform_matrix=c2w.tolist()))
train["camera_indices"] = sorted({frame["camera_index"] for frame in train["frames"]})
(dst / "transforms_train.json").write_text(json.dumps(train, indent=1))
print(f"{dst}: {len(jobs)} turned views added to the training split ({', '.join(views)}, "
      f"one training frame in {every})")
