"""Per view of `geoavatar eval RUN --split novel`: PSNR / LPIPS x10^-1 of the frames whose head-relative view yaw
lies inside the training range ("in") and beyond it ("out"), for the 160-frame subject of BENCHMARKS.md #18.

Its test segment turns the head to yaw -15 (timesteps < 140) and +18 (>= 140) (data/synth/motion.py TEST_YAW);
the training part sweeps head yaw -22..+30, i.e. views -30..+22 relative to the face. Relative yaw = camera
yaw - head yaw, so a camera turned by +30 sees a head at yaw -15 from 45 degrees: beyond anything trained.

usage: python benchmarks/novel_view_segments.py RUN/eval/novel/metrics.json ...

Since session 8 `geoavatar eval --split novel` measures this itself from the geometry, for any subject
(`view_yaw` / `view_pitch` / `trained_view` per frame, `by_view_range` per view); this script stays to reproduce
the earlier rounds' tables. On subject 0's E the two agree at yaw -30 to the digit and differ by one frame at +30.
"""
import json, sys, numpy as np
YAW = {"front": 0, "yaw+30": 30, "yaw-30": -30, "yaw+60": 60, "yaw-60": -60, "pitch+20": 0, "pitch-20": 0}
for path in sys.argv[1:]:
    r = json.load(open(path)); out = {}
    for f in r["frames"]:
        rel = YAW[f["view"]] - (-15 if f["timestep"] < 140 else 18)
        inside = -30 <= rel <= 22  # training head yaw -22..+30 -> relative -30..+22
        out.setdefault(f["view"], {}).setdefault("in" if inside else "out", []).append((f["psnr"], f["lpips"]))
    print(path.split("/")[-3], path.split("/")[-2], " ".join(
        f"{v}:" + ",".join(f"{k}{np.mean([a for a, _ in x]):.2f}/{10*np.mean([b for _, b in x]):.2f}" for k, x in sorted(s.items()))
        for v, s in out.items()))
