"""Oracles for the colour model of an avatar on a synthetic subject: what lighting alone costs at novel views.

For each surface point (mesh vertex) the best colour over the training frames is fitted by least squares
(bary-weighted pixel samples at the dataset camera, true geometry, nothing learned) in three forms:
    const  a constant (SH-0, the paper's model): albedo(p) * mean(light * occlusion) + spec(p) * mean(highlight * occlusion)
    lin    constant + linear in the point's world normal (what model.normal_shading can represent)
    quad   constant + linear + the 5 quadratic real-SH functions of the normal (second-order SH irradiance,
           9 basis functions; a model option only if it beats lin at the novel views: BENCHMARKS.md #18 fourth round)
Each renders with its texture on the TRUE geometry at every view. The light factor (ambient + Lambert of two
room lights) x occlusion and the Blinn-Phong highlight x occlusion are fitted separately (least squares is
linear, so albedo * fit(light) + spec * fit(highlight) is the per-point fit of the shaded colour). The fits of
the light factor alone, scored against the ground truth rendered without the highlight ("diffuse" columns),
show what the view-dependent highlight costs; "gt/nospec" is the ground truth against itself without it.
A small ridge (RIDGE x a vertex's sample weight, on the non-constant coefficients) keeps vertices seen over a
narrow range of normals finite; vertices no training frame shows take the mean light factor. (Before the fourth
round the light factor was clamped to 1 where ambient + Lambert exceeds it, which the ground truth does not do:
the const columns read 0.0-0.5 dB higher now.)

The first table is the first oracle of BENCHMARKS.md's #18 second round (const only; ground truth with the lights
on the rendering camera, "cam", and in the room, "world" = today's `geoavatar synth --novel-views`). The
second is per view and per segment ("in": head-relative view yaw inside the training sweep, -30..+22 degrees;
"out": beyond it), all against world-lit ground truth.

Subject SUBJECT, 160 frames, seed 0 (the commands of BENCHMARKS.md's #18 sections); the training frames and the
novel views (every EVERY-th test frame) are rendered here at SIZE px, nothing is read from disk.

usage: python benchmarks/novel_view_oracle.py [SIZE=128] [EVERY=2] [SUBJECT=0] [RIDGE=1e-3]
       (writes novel_view_oracle_SIZE.json for subject 0, novel_view_oracle_SIZE_sSUBJECT.json otherwise)
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
SUBJECT = int(sys.argv[3]) if len(sys.argv) > 3 else 0
RIDGE = float(sys.argv[4]) if len(sys.argv) > 4 else 1e-3
FRAMES = 160
ORDERS = {"const": 1, "lin": 4, "quad": 9}  # basis functions of each fit (leading columns of `basis`)

actor = actor_for_subject(SUBJECT)
subject = get_subject(SUBJECT)
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
    # shade() clamps albedo * light to 1; with albedo 0.5 the light factor (up to ~1.3) passes unclamped
    halves = torch.full((sm["normals"].shape[0], 3), 0.5)
    L = shade(halves, sm["normals"], sm["view_dirs"], LIGHTING)[:, 0] / 0.5  # ambient + Lambert
    ones = torch.ones_like(halves)
    Hl = shade(torch.zeros_like(ones), sm["normals"], sm["view_dirs"], HIGHLIGHT)[:, 0]
    return L, Hl


def compose(sm, colour, bg):
    img = bg.expand(sm["h"] * sm["w"], 3).clone()
    img[sm["pix"]] = colour
    return box_downsample(img.view(sm["h"], sm["w"], 3), R.ssaa)


def gt_image(sm, highlight=True):
    c = R.appearance.shade_samples(sm["canonical"], sm["weights"], sm["edge"], sm["normals"], sm["view_dirs"],
                                   sm["back"], sm["occ"], highlight=highlight)
    return compose(sm, c, R.background)


def basis(normals):
    """[P, 9]: 1, the normal (x, y, z), the 5 quadratic real-SH functions (unnormalised; the fit absorbs scale)."""
    x, y, z = F.normalize(normals.double(), dim=-1).unbind(-1)
    return torch.stack([torch.ones_like(x), x, y, z, x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1], -1)


spec_w = R.appearance._specular
# --- accumulate the oracle texture over the training frames -------------------------------------
acc = torch.zeros(V, 3, dtype=torch.float64)  # sum w*L*occ, sum w*H*occ, sum w
gram = torch.zeros(V, 81, dtype=torch.float64)  # per vertex sum w * phi phi^T (phi = basis of the world normal)
rhs = torch.zeros(V, 18, dtype=torch.float64)  # per vertex sum w * phi [L*occ, H*occ]
for t in range(0, test_start):
    verts = _posed_vertices(actor, gt, t, t + 1)[0]
    sm = samples(verts, camera)  # the dataset camera: its axes are the lights' (world) axes
    L, Hl = light_terms(sm)
    wts = sm["bary"].double()  # [P, 3]
    vals = torch.stack([L * sm["occ"], Hl * sm["occ"], torch.ones_like(L)], -1).double()  # [P, 3]
    phi = basis(sm["normals"])  # [P, 9]
    outer = (phi[:, :, None] * phi[:, None, :]).reshape(-1, 81)  # [P, 81]
    prod = (phi[:, :, None] * vals[:, None, :2]).reshape(-1, 18)  # [P, 18]
    for k in range(3):
        acc.index_add_(0, sm["corners"][:, k], wts[:, k:k + 1] * vals)
        gram.index_add_(0, sm["corners"][:, k], wts[:, k:k + 1] * outer)
        rhs.index_add_(0, sm["corners"][:, k], wts[:, k:k + 1] * prod)
seen = acc[:, 2]
meanL = torch.where(seen > 1e-3, acc[:, 0] / seen.clamp_min(1e-9), torch.nan)
meanH = torch.where(seen > 1e-3, acc[:, 1] / seen.clamp_min(1e-9), torch.nan)
fillL = float(meanL[~meanL.isnan()].mean())
unseen_v = meanL.isnan()
meanL = torch.nan_to_num(meanL, nan=fillL).float()
meanH = torch.nan_to_num(meanH, nan=0.0).float()
print(f"vertices {V}, unseen in training {int(unseen_v.sum())}, fill L {fillL:.3f}")


def fit(n):
    """[V, n, 2] least-squares coefficients of (light, highlight) on the first n basis functions, ridge on 2..n."""
    A = gram.view(V, 9, 9)[:, :n, :n].clone()
    b = rhs.view(V, 9, 2)[:, :n]
    ridge = torch.ones(n, dtype=torch.float64)
    ridge[0] = 1e-9
    A = A + (RIDGE * seen.clamp_min(1e-9))[:, None, None] * torch.diag(ridge)
    coef = torch.linalg.solve(A, b)  # [V, n, 2]
    coef[unseen_v] = 0.0  # no sample: the mean light factor, no highlight, no shading
    coef[unseen_v, 0, 0] = fillL
    return coef.float()


coefs = {name: fit(n) for name, n in ORDERS.items()}


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


def fitted_images(sm):
    """{name: (full, diffuse)}: each fit's image with the fitted highlight, and its light factor alone."""
    corners, bary = sm["corners"], sm["bary"]
    phi = basis(sm["normals"]).float()  # [P, 9] the point's world normal (lights' axes)
    albedo = R.appearance.albedo(sm["canonical"], sm["weights"], sm["edge"])
    spec = sm["weights"] @ spec_w / sm["weights"].sum(-1).clamp_min(1e-6)
    cavity = torch.tensor((0.16, 0.05, 0.05))
    out = {}
    for name, n in ORDERS.items():
        per_corner = (coefs[name][corners] * phi[:, None, :n, None]).sum(2)  # [P, 3 corners, 2]
        Lm, Hm = (per_corner * bary[:, :, None]).sum(1).unbind(-1)  # [P] each
        diffuse = albedo * Lm[:, None]
        images = []
        for c in (diffuse + (spec * Hm)[:, None], diffuse):
            c = torch.where(sm["back"][:, None], cavity * sm["occ"][:, None], c).clamp(0, 1)
            images.append(compose(sm, c, R.background))
        out[name] = tuple(images)
    return out


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
        g_diffuse = gt_image(sm_world, highlight=False)
        r = rows.setdefault(name, [])
        # segment as benchmarks/novel_view_segments.py: the test segment's head yaw is -15 (t < 140) or +18
        rel = yaw - (-15.0 if t < 140 else 18.0)
        rec = dict(t=t, head_yaw=head_yaw_deg(t), rel_yaw=yaw - head_yaw_deg(t), segment="in" if -30 <= rel <= 22 else "out",
                   oracle_vs_gt_cam=psnr(o_cam, g_cam), oracle_vs_gt_world=psnr(o_cam, g_world),
                   gtcam_vs_gtworld=psnr(g_cam, g_world), gt_vs_nospec=psnr(g_world, g_diffuse), unseen=unseen)
        for fname, (full, diffuse) in fitted_images(sm_world).items():
            rec[fname] = psnr(full, g_world)
            rec[fname + "_diffuse"] = psnr(diffuse, g_diffuse)
        r.append(rec)

print(f"{'view':9s} {'n':>3s} {'oracle/GTcam':>12s} {'oracle/GTworld':>14s} {'GTcam/GTworld':>13s} {'unseen%':>8s}")
out = {}
for name, r in rows.items():
    m = {k: float(np.mean([x[k] for x in r])) for k in ("oracle_vs_gt_cam", "oracle_vs_gt_world", "gtcam_vs_gtworld", "unseen")}
    out[name] = dict(mean=m, frames=r)
    print(f"{name:9s} {len(r):3d} {m['oracle_vs_gt_cam']:12.2f} {m['oracle_vs_gt_world']:14.2f} "
          f"{m['gtcam_vs_gtworld'] if math.isfinite(m['gtcam_vs_gtworld']) else float('inf'):13.2f} {100 * m['unseen']:8.2f}")
for name, r in rows.items():
    print(name, " ".join(f"[t{x['t']} rel{x['rel_yaw']:+.0f} {x['oracle_vs_gt_cam']:.1f}/{x['oracle_vs_gt_world']:.1f}]" for x in r))

keys = [*ORDERS, *(k + "_diffuse" for k in ORDERS), "gt_vs_nospec"]
print(f"\nworld-lit ground truth, ridge {RIDGE:g}; PSNR of each fit (with its fitted highlight) against the GT, "
      "of its light factor alone against the GT without the highlight (_diffuse), and GT vs GT without highlight")
print(f"{'view':9s} {'seg':>4s} {'n':>3s} " + " ".join(f"{k:>13s}" for k in keys))
for name, r in rows.items():
    for seg in ("all", "in", "out"):
        sel = [x for x in r if seg == "all" or x["segment"] == seg]
        if not sel:
            continue
        m = {k: float(np.mean([x[k] for x in sel])) for k in keys}
        out[name]["mean_" + seg] = m
        print(f"{name:9s} {seg:>4s} {len(sel):3d} " + " ".join(f"{m[k]:13.2f}" for k in keys))
suffix = "" if SUBJECT == 0 else f"_s{SUBJECT}"
json.dump(out, open(f"novel_view_oracle_{SIZE}{suffix}.json", "w"), indent=1)
