"""How layered a run's avatar is: the spread of its Gaussians' depths along each pixel's ray, and their offset from
the head mesh, at the novel split's views (issue #18: a view-independent colour composited from semi-transparent
layers at different depths looks right from the training camera only).

Per pixel the rasterizer's alpha-weighted moments of the camera-space depth z of the Gaussian centres (rendered as
colours (z - z0, (z - z0)^2, 1) on black, z0 the frame's mean mesh depth, millimetres) give the mean depth
E[z] and the spread sd[z] = sqrt(E[z^2] - E[z]^2) of what the pixel composites. Scored on the pixels where the posed
head mesh's bare face is visible (APS parts face, nose, eye_region: no hair, beard-free on subjects 0-1, where the
generated actor's surface is the head mesh) and the render is opaque (alpha > 0.9): median and mean of sd[z] and of
|E[z] - mesh depth| (mm), per view; and the share of the pixel's colour weight that comes from Gaussians whose centre
lies more than TOL mm behind the visible mesh surface at the pixel it projects to ("behind": hidden surfaces showing
through), split into Gaussians of the mouth structure ("mouth") and the others by whether their face turns its back
on the camera ("away": the far side of the head) or not ("facing": Gaussians sunk below a visible surface).
(Centres, not the Gaussians' extent: a flat splat crossing the ray off its centre counts at its centre's depth.)

usage: python benchmarks/novel_view_depth.py RUN [VIEWS=front,yaw+30,yaw-30] [PER_VIEW=all] [TOL=5]   (exact-parameter datasets: the mesh is the truth there)
"""

import sys
from collections import defaultdict

import numpy as np
import torch

from geoavatar.avatar.render import pose_avatar, rasterize_gaussians
from geoavatar.eval.evaluate import render_run_frames
from geoavatar.head.regions import face_parts
from geoavatar.render.camera import Camera, world_to_camera
from geoavatar.render.mesh import rasterize_mesh
from geoavatar.train.checkpoint import load_run, open_run_dataset
from geoavatar.train.mesh_prior import behind_surface

torch.set_num_threads(1)
run = load_run(sys.argv[1])
views = sys.argv[2].split(",") if len(sys.argv) > 2 else ["front", "yaw+30", "yaw-30"]
ds = open_run_dataset(run, "novel")
per_view = int(sys.argv[3]) if len(sys.argv) > 3 else None
TOL = float(sys.argv[4]) if len(sys.argv) > 4 else 5.0
indices = [i for v in views for i in [j for j, f in enumerate(ds.frames) if f.view == v][:per_view]]
parts = face_parts(run.head.data)
mouth_structure = torch.from_numpy(parts.part_of_face < 0)  # [F] F_m: teeth, palate, mouth floor
bare = torch.from_numpy(np.isin(parts.part_of_face, [parts.part_names.index(n) for n in ("face", "nose", "eye_region")]))
stats = defaultdict(lambda: defaultdict(list))
for fr in render_run_frames(run, ds, indices):
    item = fr.item
    h, w = fr.pred.shape[:2]
    camera = Camera(item["viewmat"], item["K"], item["width"], item["height"])
    frags = rasterize_mesh(world_to_camera(fr.vertices, item["viewmat"]), run.head.faces, item["K"], w, h)
    visible = frags.face_id >= 0
    z0 = float(frags.depth[visible].mean())
    camera_centre = -item["viewmat"][:3, :3].T @ item["viewmat"][:3, 3]  # [3] world
    g = pose_avatar(run.avatar, run.head, fr.params, fr.T, run.deformer).gaussians
    z = (world_to_camera(g.means, item["viewmat"])[..., 2] - z0) * 1000.0  # [N] mm
    moments = torch.stack([z, z * z, torch.ones_like(z)], -1)
    with torch.no_grad():
        res = rasterize_gaussians(g._replace(colors=moments), camera, None, check_values=False)
        # each centre against the mesh depth at the pixel it projects to (the training loss's test, mesh_prior.py)
        behind = behind_surface(world_to_camera(g.means, item["viewmat"]), frags.depth, item["K"], TOL / 1000.0)
        in_mouth = mouth_structure[run.avatar.binding]
        normal = g.frames.rotation[run.avatar.binding, :, 1]  # [N, 3] world normal of each Gaussian's face
        away = (normal * (g.means - camera_centre)).sum(-1) > 0  # its face turns its back on the camera
        other = behind & ~in_mouth
        flags = torch.stack([(behind & in_mouth).float(), (other & away).float(), (other & ~away).float()], -1)
        layered = rasterize_gaussians(g._replace(colors=flags), camera, None, check_values=False).rgb
    alpha = res.alpha[..., 0]
    keep = visible & bare[frags.face_id.clamp_min(0)] & (alpha > 0.9)
    mean = res.rgb[..., 0] / alpha.clamp_min(1e-6)
    spread = (res.rgb[..., 1] / alpha.clamp_min(1e-6) - mean**2).clamp_min(0).sqrt()
    offset = (mean - (frags.depth - z0) * 1000.0).abs()
    view = ds.frames[fr.index].view
    stats[view]["sd"].append(spread[keep].numpy())
    stats[view]["off"].append(offset[keep].numpy())
    for k, name in enumerate(("behind_mouth", "behind_away", "behind_facing")):
        stats[view][name].append((layered[..., k] / alpha.clamp_min(1e-6))[keep].numpy())

print(f"{sys.argv[1]}: depth of the composited Gaussian centres on opaque head-mesh pixels (mm), per view")
print(f"{'view':9s} {'pixels':>7s} {'sd median':>10s} {'sd mean':>8s} {'|offset| median':>16s} {'|offset| mean':>14s}"
      f" {'behind %':>9s} {'mouth %':>8s} {'away %':>7s} {'facing %':>9s}  (weight share, TOL {TOL:g} mm)")
for view in views:
    sd, off = np.concatenate(stats[view]["sd"]), np.concatenate(stats[view]["off"])
    share = {k: 100 * np.concatenate(stats[view][k]).mean() for k in ("behind_mouth", "behind_away", "behind_facing")}
    print(f"{view:9s} {sd.size:7d} {np.median(sd):10.2f} {sd.mean():8.2f} {np.median(off):16.2f} {off.mean():14.2f}"
          f" {sum(share.values()):9.1f} {share['behind_mouth']:8.1f} {share['behind_away']:7.1f} {share['behind_facing']:9.1f}")
