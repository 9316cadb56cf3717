"""Experiment of issue #18 (fourth round): back-face culling of Gaussians during training and evaluation.

A Gaussian whose face normal points away from the camera (cos(normal, to-camera) < MARGIN) gets opacity 0 in that
render, except the mouth structure's (teeth, palate, floor are seen through the open mouth). Patches render_avatar
in the trainer and in eval (not in the other apps), then runs the CLI with the remaining arguments. Not a model
option: it lowered the front test PSNR by 1.0-1.3 dB on subject 0 (BENCHMARKS.md #18 fourth round), so it stays an
experiment. The far side of the head is what the cull removes; novel_view_depth.py measures how much of a pixel's
colour comes from there.

usage: python benchmarks/backface_cull_experiment.py train --data D --out RUN --preset E --steps 1500 --resolution 128
       python benchmarks/backface_cull_experiment.py eval RUN [--split novel] --no-floaters     (CULL_MARGIN env, default -0.3)
"""
import os
import sys

import torch
import torch.nn.functional as F
import geoavatar.avatar.render as R
import geoavatar.train.trainer as trainer
import geoavatar.eval.evaluate as evaluate
from geoavatar.head.regions import face_parts

MARGIN = float(os.environ.get("CULL_MARGIN", "-0.3"))
_mouth = {}


def render_avatar_culled(avatar, head, params, camera, timestep=None, deformer=None, background=None,
                         backend="auto", check_values=True):
    posed = R.pose_avatar(avatar, head, params, timestep, deformer)
    g = posed.gaussians
    key = id(head)
    if key not in _mouth:
        _mouth[key] = torch.from_numpy(face_parts(head.data).part_of_face < 0)
    mouth = _mouth[key].to(avatar.binding.device)[avatar.binding]  # [N]
    vm = camera.viewmat.to(g.means)
    centre = -vm[:3, :3].T @ vm[:3, 3]
    normal = g.frames.rotation[..., avatar.binding, :, 1].detach()
    cos = (normal * F.normalize(centre - g.means.detach(), dim=-1)).sum(-1)
    keep = (cos > MARGIN) | mouth
    g = g._replace(opacities=g.opacities * keep.to(g.opacities))
    result = R.rasterize_gaussians(g, camera, background, backend, check_values)
    return R.AvatarRender(result, g, posed.vertices)


trainer.render_avatar = render_avatar_culled
evaluate.render_avatar = render_avatar_culled
from geoavatar.cli import main  # noqa: E402  (after the patches)
sys.argv[0] = "geoavatar"
sys.exit(main(sys.argv[1:]))
