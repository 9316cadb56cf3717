"""Oracle for a view-independent (SH-0) avatar on a synthetic subject.

For each surface point the best constant colour over the training frames (L2: the pixel-weighted mean of
its shaded colour) is albedo(p) * mean(light * occlusion) + spec(p) * mean(highlight * occlusion), the
means per vertex (bary-weighted pixel splats over the training frames at the dataset camera). The oracle
renders with that texture on the TRUE geometry; its PSNR against the ground truth is the ceiling of any
unrelightable avatar with exact geometry: what lighting alone costs. Novel views are scored against the
GT as written (lights fixed to the camera that renders) and with lights fixed to the dataset camera
(world-fixed, as in a real capture room).

Subject 0, 160 frames, seed 0 (the commands of BENCHMARKS.md's #18 section); the training frames and the
novel views (every EVERY-th test frame) are rendered here at SIZE px, nothing is read from disk.

usage: python benchmarks/novel_view_oracle.py [SIZE=128] [EVERY=2]   (writes novel_view_oracle_SIZE.json)
"""

import json
import math
import sys

import numpy as np
import torch
import torch.nn.functional as F

from geoavatar.data.synth.actor import actor_for_subject
from geoavatar.data.synth.appearance import HIGHLIGHT, LIGHTING, MATERIAL_INDEX
from geoavatar.data.synth.generate import NOVEL_VIEWS, motion_to_params, _posed_vertices
from geoavatar.data.synth.motion import script_motion
from geoavatar.data.synth.render import ActorRenderer, _MOUTH_MATERIALS, frontal_camera, orbit_camera
from geoavatar.data.synth.subjects import get_subject
from geoavatar.head.regions import skull_centre
from geoavatar.render.camera import world_to_camera
from geoavatar.render.mesh import box_downsample, face_normals, rasterize_mesh, scale_intrinsics, shade, vertex_normals

torch.set_num_threads(1)
SIZE = int(sys.argv[1]) if len(sys.argv) > 1 else 128
EVERY = int(sys.argv[2]) if len(sys.argv) > 2 else 2
FRAMES = 160

actor = actor_for_subject(0)
subject = get_subject(0)
camera = frontal_camera(actor, SIZE)
R = ActorRenderer(actor, camera, subject.background_rgb, ssaa=2)
motion = script_motion(FRAMES, 0, 25.0)
gt, _ = motion_to_params(motion, actor)
test_start = motion.test_start
V = actor.canonical.shape[0]


def samples(vertices, cam, light_viewmat=None):
    """Per covered hi-res pixel: everything shading needs; normals/view dirs in the light's camera frame."""
    s = R.ssaa
    w, h = cam.width * s, cam.height * s
    K_hi = scale_intrinsics(cam.K, s)
    vc = world_to_camera(vertices.float(), cam.viewmat)
    frags = rasterize_mesh(vc, R.faces, K_hi, w, h)
    covered = frags.face_id.reshape(-1) >= 0
    pix = torch.nonzero(covered).squeeze(1)
    fid = frags.face_id.reshape(-1)[pix]
    bary = frags.bary.reshape(-1, 3)[pix]
    corners = R.faces[fid]

    def lerp(a):
        return (a[corners] * bary[:, :, None]).sum(1)

    attrs = lerp(R.vertex_attrs)
    canonical, weights, edge = attrs[:, :3], attrs[:, 3:-1], attrs[:, -1]
    normals = lerp(vertex_normals(vc, R.faces))
    position = lerp(vc)
    view_dirs = F.normalize(-position, dim=-1)
    geometric = face_normals(vc, R.faces)[fid]
    back = ((geometric * view_dirs).sum(-1) < 0) & R.cavity[fid]
    depth_in = (R.mouth_z - canonical[:, 2]).clamp_min(0.0)
    mw = weights[:, _MOUTH_MATERIALS].sum(-1).clamp(0, 1)
    inside = torch.where(back, torch.ones_like(mw), mw)
    occ = 1.0 - inside * 0.75 * (1.0 - torch.exp(-depth_in / 0.015))
    if light_viewmat is not None:  # rotate camera-space vectors into the light camera's axes
        rot = light_viewmat[:3, :3].double() @ cam.viewmat[:3, :3].double().T
        normals = normals @ rot.float().T
        view_dirs = view_dirs @ rot.float().T
    return dict(pix=pix, corners=corners, bary=bary, canonical=canonical, weights=weights, edge=edge,
                normals=normals, view_dirs=view_dirs, back=back, occ=occ, h=h, w=w, covered=covered)


def light_terms(sm):
    ones = torch.ones(sm["normals"].shape[0], 3)
    L = shade(ones, sm["normals"], sm["view_dirs"], LIGHTING)[:, 0]  # ambient + lambert (no clamp issue: <1.3?)
    Hl = shade(torch.zeros_like(ones), sm["normals"], sm["view_dirs"], HIGHLIGHT)[:, 0]
    return L, Hl


def compose(sm, colour, bg):
    img = bg.expand(sm["h"] * sm["w"], 3).clone()
    img[sm["pix"]] = colour
    return box_downsample(img.view(sm["h"], sm["w"], 3), R.ssaa)


def gt_image(sm):
    c = R.appearance.shade_samples(sm["canonical"], sm["weights"], sm["edge"], sm["normals"], sm["view_dirs"],
                                   sm["back"], sm["occ"])
    return compose(sm, c, R.background)


spec_w = R.appearance._specular
# --- accumulate the oracle texture over the training frames -------------------------------------
acc = torch.zeros(V, 3, dtype=torch.float64)  # sum w*L*occ, sum w*H*occ, sum w
for t in range(0, test_start):
    verts = _posed_vertices(actor, gt, t, t + 1)[0]
    sm = samples(verts, camera)
    L, Hl = light_terms(sm)
    wts = sm["bary"].double()  # [P, 3]
    vals = torch.stack([L * sm["occ"], Hl * sm["occ"], torch.ones_like(L)], -1).double()  # [P, 3]
    for k in range(3):
        acc.index_add_(0, sm["corners"][:, k], wts[:, k:k + 1] * vals)
seen = acc[:, 2]
meanL = torch.where(seen > 1e-3, acc[:, 0] / seen.clamp_min(1e-9), torch.nan)
meanH = torch.where(seen > 1e-3, acc[:, 1] / seen.clamp_min(1e-9), torch.nan)
fillL = float(meanL[~meanL.isnan()].mean())
unseen_v = meanL.isnan()
meanL = torch.nan_to_num(meanL, nan=fillL).float()
meanH = torch.nan_to_num(meanH, nan=0.0).float()
print(f"vertices {V}, unseen in training {int(unseen_v.sum())}, fill L {fillL:.3f}")


def oracle_image(sm):
    corners, bary = sm["corners"], sm["bary"]
    Lm = (meanL[corners] * bary).sum(1)
    Hm = (meanH[corners] * bary).sum(1)
    unseen = (unseen_v[corners].float() * bary).sum(1) > 0.5
    albedo = R.appearance.albedo(sm["canonical"], sm["weights"], sm["edge"])
    spec = sm["weights"] @ spec_w / sm["weights"].sum(-1).clamp_min(1e-6)
    c = albedo * Lm[:, None] + (spec * Hm)[:, None]
    cavity = torch.tensor((0.16, 0.05, 0.05))
    c = torch.where(sm["back"][:, None], cavity * sm["occ"][:, None], c).clamp(0, 1)
    return compose(sm, c, R.background), float(unseen.float().mean())


def psnr(a, b):
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


def head_yaw_deg(t):
    return math.degrees(float(motion.yaw[t]))


rows = {}
for t in range(test_start, FRAMES, EVERY):
    verts = _posed_vertices(actor, gt, t, t + 1)[0]
    centre = skull_centre(verts, actor.head)
    views = [("front", 0.0, 0.0, camera)] + [(n, y, p, orbit_camera(camera, y, p, centre)) for _, n, y, p in NOVEL_VIEWS]
    for name, yaw, pitch, cam in views:
        sm_cam = samples(verts, cam)  # lights with the rendering camera (the GT as written)
        sm_world = samples(verts, cam, light_viewmat=camera.viewmat)  # lights fixed to the dataset camera
        g_cam = gt_image(sm_cam)
        g_world = gt_image(sm_world)
        o_cam, unseen = oracle_image(sm_cam)  # oracle colour is view-independent: same for both
        r = rows.setdefault(name, [])
        r.append(dict(t=t, head_yaw=head_yaw_deg(t), rel_yaw=yaw - head_yaw_deg(t),
                      oracle_vs_gt_cam=psnr(o_cam, g_cam), oracle_vs_gt_world=psnr(o_cam, g_world),
                      gtcam_vs_gtworld=psnr(g_cam, g_world), unseen=unseen))

print(f"{'view':9s} {'n':>3s} {'oracle/GTcam':>12s} {'oracle/GTworld':>14s} {'GTcam/GTworld':>13s} {'unseen%':>8s}")
out = {}
for name, r in rows.items():
    m = {k: float(np.mean([x[k] for x in r])) for k in ("oracle_vs_gt_cam", "oracle_vs_gt_world", "gtcam_vs_gtworld", "unseen")}
    out[name] = dict(mean=m, frames=r)
    print(f"{name:9s} {len(r):3d} {m['oracle_vs_gt_cam']:12.2f} {m['oracle_vs_gt_world']:14.2f} "
          f"{m['gtcam_vs_gtworld'] if math.isfinite(m['gtcam_vs_gtworld']) else float('inf'):13.2f} {100 * m['unseen']:8.2f}")
for name, r in rows.items():
    print(name, " ".join(f"[t{x['t']} rel{x['rel_yaw']:+.0f} {x['oracle_vs_gt_cam']:.1f}/{x['oracle_vs_gt_world']:.1f}]" for x in r))
json.dump(out, open(f"novel_view_oracle_{SIZE}.json", "w"), indent=1)
