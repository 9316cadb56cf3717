"""Stills of the speech-driven held-out frames: ground truth | tracked render | speech-driven render, where the tracked
mouth opens most and where it is closed (rows), as `geoavatar eval RUN --speech` renders them (the tracked head pose
and gaze, the voice model's expression and jaw from the held-out frames' own sound, T = 0).

    .venv/bin/python benchmarks/speech_stills.py RUN --out docs/images/speech_stills.jpg [--size 256]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--size", type=int, default=256, help="side of each picture")
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    import torch
    from PIL import Image, ImageDraw

    from geoavatar.avatar import render_avatar
    from geoavatar.data.dataset import item_camera, item_to
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.eval.speech_run import _segment_inputs, _test_items, spoken_params
    from geoavatar.head.params import HeadParams
    from geoavatar.imaging import to_uint8
    from geoavatar.render import composite_target
    from geoavatar.train.checkpoint import open_run
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice import VoiceModel
    from geoavatar.voice.face import FaceProbe

    run = open_run(args.run, "cpu")
    voice = VoiceModel.load(args.run)
    frames = RunFrames(run)
    sound = read_dataset_sound(run.info.data_root)
    test = sorted(run.info.timesteps["test"], key=lambda t: sound.frame_times[t])
    inputs, tracked, _ = _segment_inputs(run, frames, sound, test, voice.expr_dims)
    spoken = voice.predict_features(inputs.test_mel, torch.from_numpy(inputs.test_centres))
    probe = FaceProbe(run.head, frames.identity())
    with torch.no_grad():
        opening = probe.opening(torch.as_tensor(tracked.expr), torch.as_tensor(tracked.jaw)).numpy()
    rows = {"mouth open most": int(opening.argmax()), "mouth closed": int(opening.argmin())}
    dataset, index_of = _test_items(run, None)
    pictures = []
    for label, row in rows.items():
        item = item_to(dataset[index_of[test[row]]], run.device)
        params = HeadParams.from_npz(item["params"])
        driven = spoken_params(params, spoken, row)
        camera = item_camera(item)
        with torch.no_grad():
            panels = [composite_target(item["image"], item["mask"], item["background"])]
            for p in (params, driven):
                panels.append(render_avatar(run.avatar, run.head, p, camera, None, run.deformer,
                                            item["background"]).result.rgb.clamp(0, 1))
        strip = np.concatenate([np.asarray(Image.fromarray(to_uint8(p)).resize((args.size, args.size)))
                                for p in panels], axis=1)
        image = Image.fromarray(strip)
        draw = ImageDraw.Draw(image)
        draw.text((4, 4), f"t={test[row]} {label}: ground truth | tracked | speech-driven", fill=(255, 255, 0))
        pictures.append(np.asarray(image))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(pictures, axis=0)).save(args.out, quality=90)
    print(f"wrote {args.out}: rows {rows} (held-out rows), tracked opening {opening.max() * 1000:.1f} / "
          f"{opening.min() * 1000:.1f} mm")


if __name__ == "__main__":
    main()
