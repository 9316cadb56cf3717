"""Two probes behind the per-component explanation of the ablation (issue #13, BENCHMARKS.md).

coverage: how much of its own triangle a Gaussian centre can reach without paying L_reg, per threshold tau:
    the share of each face's area within tau * k of the face centre (k = GaussianAvatars' face scale, the
    unit of local means), over the faces of the head model's template.

    python benchmarks/ablation_probes.py coverage [--head openhead] [--taus 0.1 0.2 0.5 1.0]

polar: where trained runs keep their Gaussians in the polar coordinates of Sec. 3, per face set: the share
    beyond tau_r, the share L_angle would penalise (r > tau_r and phi > tau_phi, measured from the face
    normal, one-sided and two-sided) and the share below the face plane (phi > 90 deg), counts and
    opacity-weighted.

    python benchmarks/ablation_probes.py polar RUN [RUN ...]
"""

from __future__ import annotations

import argparse
import math

import torch

from geoavatar.avatar.aps import BASELINE, FLEXIBLE, MOUTH, RIGID
from geoavatar.avatar.binding import face_frames, polar_coordinates
from geoavatar.head import load_head_data
from geoavatar.train.checkpoint import load_checkpoint

SET_NAMES = {RIGID: "rigid", FLEXIBLE: "flexible", MOUTH: "mouth", BASELINE: "one set (A)"}


def coverage(head: str, taus: list[float], samples: int = 4000) -> None:
    data = load_head_data(head, mouth="geoavatar")
    vertices = torch.as_tensor(data.v_template, dtype=torch.float32)  # [V, 3]
    faces = torch.as_tensor(data.faces).long()  # [F, 3]
    frames = face_frames(vertices, faces)
    u = torch.rand(samples, 2, generator=torch.Generator().manual_seed(0))  # uniform in the unit triangle
    u = torch.where((u.sum(1) > 1)[:, None], 1 - u, u)
    corners = vertices[faces]  # [F, 3, 3]
    points = (corners[:, None, 0] + u[None, :, :1] * (corners[:, None, 1] - corners[:, None, 0])
              + u[None, :, 1:] * (corners[:, None, 2] - corners[:, None, 0]))  # [F, S, 3]
    reach = (points - frames.centre[:, None]).norm(dim=-1) / frames.scale[:, None]  # [F, S] in units of k
    corner_reach = (corners - frames.centre[:, None]).norm(dim=-1) / frames.scale[:, None]  # [F, 3]
    print(f"{head}: {faces.shape[0]} faces; a corner lies {corner_reach.median():.2f} k from the face centre (median)")
    print("| tau | share of a face's area within tau k of its centre: median | mean |")
    print("|---:|---:|---:|")
    for tau in taus:
        share = (reach <= tau).float().mean(1)  # [F]
        print(f"| {tau:g} | {share.median():.1%} | {share.mean():.1%} |")


def polar(runs: list[str], tau_r: float = 0.1, tau_phi: float = 0.78) -> None:
    print("| run | set | Gaussians | r > τ_r | r > τ_r, φ > 45° | (opacity-weighted) | r > τ_r, φ > 90° "
          "| two-sided: r > τ_r, φ' > 45° |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for run in runs:
        ckpt = load_checkpoint(f"{run}/checkpoints/final.pt")
        avatar, ckpt_sets = ckpt["avatar"], ckpt["face_sets"]
        means, binding = avatar["params.means"], avatar["binding"].long()  # [N, 3], [N]
        opacity = torch.sigmoid(avatar["params.opacities"])  # [N]
        r, phi = polar_coordinates(means)
        _, phi_line = polar_coordinates(means, two_sided=True)
        sets = torch.as_tensor(ckpt_sets)[binding] if ckpt_sets is not None else torch.full_like(binding, BASELINE)
        far = r > tau_r
        for s in sorted(set(sets.tolist())) + [None]:
            member = torch.ones_like(far) if s is None else sets == s
            n = int(member.sum())
            hit = member & far & (phi > tau_phi)
            print(f"| {run} | {SET_NAMES.get(s, 'all')} | {n} | {(member & far).sum() / n:.1%} | {hit.sum() / n:.1%} "
                  f"| {opacity[hit].sum() / opacity[member].sum():.1%} | {(member & far & (phi > math.pi / 2)).sum() / n:.1%} "
                  f"| {(member & far & (phi_line > tau_phi)).sum() / n:.1%} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="probe", required=True)
    c = sub.add_parser("coverage")
    c.add_argument("--head", default="openhead")
    c.add_argument("--taus", type=float, nargs="+", default=[0.1, 0.2, 0.5, 1.0, 2.0])
    p = sub.add_parser("polar")
    p.add_argument("runs", nargs="+")
    args = parser.parse_args()
    if args.probe == "coverage":
        coverage(args.head, args.taus)
    else:
        polar(args.runs)


if __name__ == "__main__":
    main()
