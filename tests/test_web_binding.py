"""The player's binding maths (web/src/binding.js, run in node) against avatar/binding.py on the same numbers:
face frames of posed head meshes (centre, scale k, rotation and its quaternion) and the clip's dequantisation."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from geoavatar.avatar.binding import face_frames
from geoavatar.geometry import quaternion_to_matrix
from geoavatar.head import load_head_model
from geoavatar.head.params import HeadParams
from geoavatar.web.pack import quantise_clip

BINDING_JS = Path(__file__).resolve().parents[1] / "web" / "src" / "binding.js"
NODE_SCRIPT = """
import { faceFrames, dequantiseFrame } from %s;
let input = "";
process.stdin.on("data", (chunk) => { input += chunk; });
process.stdin.on("end", () => {
  const job = JSON.parse(input);
  const frames = faceFrames(Float32Array.from(job.vertices), Uint32Array.from(job.faces));
  const decoded = dequantiseFrame(Uint16Array.from(job.codes), job.frame, job.vertexCount, job.offset, job.step);
  process.stdout.write(JSON.stringify({ frames: Array.from(frames), decoded: Array.from(decoded) }));
});
"""

pytestmark = pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed (Node 20: the player's maths)")


def run_node(job: dict) -> dict:
    script = NODE_SCRIPT % json.dumps(BINDING_JS.as_uri())
    done = subprocess.run(["node", "--input-type=module", "-e", script], input=json.dumps(job), capture_output=True,
                          text=True, timeout=60, check=True)
    return json.loads(done.stdout)


def posed_heads() -> tuple[torch.Tensor, torch.Tensor]:
    """[2, V, 3] OpenHead with its mouth, posed twice (turned, jaw open, expressions), and its faces [F, 3]."""
    head = load_head_model("openhead", mouth="geoavatar")
    generator = torch.Generator().manual_seed(0)
    params = HeadParams(shape=torch.randn(head.num_shape, generator=generator) * 0.5,
                        expr=torch.randn(2, head.num_expr, generator=generator),
                        rotation=torch.tensor([[0.1, 0.6, -0.05], [-0.2, -0.4, 0.1]]),
                        neck_pose=torch.zeros(2, 3), jaw_pose=torch.tensor([[0.3, 0.0, 0.0], [0.05, 0.0, 0.0]]),
                        eyes_pose=torch.zeros(2, 6), translation=torch.tensor([[0.0, 0.0, 0.0], [0.01, -0.02, 0.3]]))
    with torch.no_grad():
        return head.forward_params(params).vertices, head.faces


def test_face_frames_and_dequantisation_match_python():
    vertices, faces = posed_heads()  # [2, V, 3], [F, 3]
    clip = quantise_clip(vertices)
    decoded_python = torch.from_numpy(clip.vertices()[1])  # [V, 3] what the page decodes for frame 1
    out = run_node({"vertices": decoded_python.flatten().tolist(), "faces": faces.flatten().tolist(),
                    "codes": clip.codes.flatten().tolist(), "frame": 1, "vertexCount": int(vertices.shape[1]),
                    "offset": clip.offset.tolist(), "step": clip.step.tolist()})

    decoded = np.asarray(out["decoded"], dtype=np.float32).reshape(-1, 3)
    np.testing.assert_allclose(decoded, decoded_python.numpy(), atol=1e-7)
    assert np.abs(decoded - vertices[1].numpy()).max() < 1e-5  # quantisation: micrometres

    expected = face_frames(decoded_python.double(), faces)
    js = torch.tensor(out["frames"], dtype=torch.float64).reshape(-1, 8)  # [F, 8]: C, k, q (x y z w)
    np.testing.assert_allclose(js[:, :3], expected.centre, atol=1e-6)
    np.testing.assert_allclose(js[:, 3], expected.scale, rtol=1e-5)
    quat = js[:, [7, 4, 5, 6]]  # w x y z
    np.testing.assert_allclose(quat, expected.quaternion, atol=2e-5)  # both with w >= 0
    np.testing.assert_allclose(quaternion_to_matrix(quat), expected.rotation, atol=2e-5)
    normals = expected.rotation[:, :, 1]  # the shading's normal: R's second column
    assert (quaternion_to_matrix(quat)[:, :, 1] * normals).sum(-1).min() > 1 - 1e-6


def test_quantised_clip_round_trip_and_bad_input():
    vertices = torch.randn(3, 10, 3) * 0.1
    clip = quantise_clip(vertices)
    assert clip.codes.dtype == np.uint16 and clip.codes.shape == (3, 10, 3)
    assert np.abs(clip.vertices() - vertices.numpy()).max() <= clip.step.max() / 2 + 1e-7
    with pytest.raises(ValueError, match="NaN"):
        quantise_clip(torch.full((1, 2, 3), float("nan")))
    with pytest.raises(ValueError, match=r"\[T, V, 3\]"):
        quantise_clip(torch.zeros(4, 3))


@pytest.mark.skipif(not (BINDING_JS.parents[1] / "node_modules" / "esbuild").is_dir(),
                    reason="web/node_modules is not installed (make web installs it); the committed bundle is used")
def test_the_committed_bundle_is_built_from_the_current_source(tmp_path):
    subprocess.run(["node", "build.mjs"], cwd=BINDING_JS.parents[1], env={**os.environ, "GEOAVATAR_WEB_OUT": str(tmp_path)},
                   check=True, capture_output=True, timeout=120)
    committed = Path(__file__).resolve().parents[1] / "geoavatar" / "web" / "static" / "player.js"
    assert (tmp_path / "player.js").read_bytes() == committed.read_bytes(), "web/src changed: run make web"


def test_avatar_bin_holds_the_splats_in_export_order_with_pose_rows_for_the_moving_ones():
    """avatar.bin decoded as web/src/player.js reads it: anchors (float32), rows (float16) and pose rows all follow
    one order, the splats on moving faces first, and only those P carry pose rows."""
    from geoavatar.avatar.model import GaussianAvatar
    from geoavatar.render.camera import Camera
    from geoavatar.web.pack import ANCHOR_FLOATS, player_assets, pose_table, splat_order, splat_table

    vertices, faces = posed_heads()
    moving = torch.zeros(len(faces), dtype=torch.bool)
    moving[torch.randperm(len(faces), generator=torch.Generator().manual_seed(2))[: len(faces) // 2]] = True
    avatar = GaussianAvatar(faces, normal_shading=True, moving=moving)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for param in avatar.params.values():
            param.copy_(torch.randn(param.shape, generator=g) * 0.3)
    camera = Camera(torch.eye(4), torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]]), 64, 64)
    assets = player_assets(avatar, quantise_clip(vertices), 25.0, camera, {}, (1.0, 1.0, 1.0), [0, 1], "test",
                           pose_codes=torch.zeros(2, 6))
    n, f, posed = avatar.num_gaussians, len(faces), assets.manifest["avatar"]["posed"]
    on_moving = moving[avatar.binding].numpy()  # [N]
    assert posed == on_moving.sum() and 0 < posed < n
    data = assets.avatar_bytes
    assert len(data) == n * 16 + n * 40 + f * 12 + posed * 72
    anchors = np.frombuffer(data, "<f4", n * 4).reshape(n, 4)
    rows = np.frombuffer(data, "<f2", n * 20, offset=n * 16).reshape(n, 20)
    face_ids = np.frombuffer(data, "<u4", f * 3, offset=n * 56).reshape(f, 3)
    poses = np.frombuffer(data, "<f2", posed * 36, offset=n * 56 + f * 12).reshape(posed, 36)
    order, order_posed = splat_order(avatar)
    assert order_posed == posed and on_moving[order[:posed]].all() and not on_moving[order[posed:]].any()
    assert (np.diff(order[:posed]) > 0).all() and (np.diff(order[posed:]) > 0).all()  # stable within each part
    table = splat_table(avatar)[order]  # [N, 24]
    np.testing.assert_array_equal(anchors, table[:, :ANCHOR_FLOATS])  # face indices and local means exact
    np.testing.assert_array_equal(rows, table[:, ANCHOR_FLOATS:].astype(np.float16))  # float16's rounding, no more
    np.testing.assert_array_equal(poses, pose_table(avatar)[order[:posed]])
    np.testing.assert_array_equal(face_ids, faces.numpy())


def test_the_splat_table_holds_what_the_gpu_needs_to_place_the_avatar():
    """The table's layout read back the way web/src/generator.js reads it (face frames of binding.py) gives the
    model's own global Gaussians: means, rotations, scales, opacities and shaded colours."""
    from geoavatar.avatar.model import GaussianAvatar
    from geoavatar.geometry import quaternion_multiply
    from geoavatar.web.pack import splat_table

    vertices, faces = posed_heads()
    avatar = GaussianAvatar(faces, normal_shading=True)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, param in avatar.params.items():
            param.copy_(torch.randn(param.shape, generator=g) * 0.3)
    mesh = vertices[0]
    with torch.no_grad():
        expected = avatar(mesh)
    table = torch.from_numpy(splat_table(avatar)).double()  # [N, 24]
    frames = face_frames(mesh.double(), faces)
    face = table[:, 3].long()
    rotation, centre, k = frames.rotation[face], frames.centre[face], frames.scale[face]  # per splat
    means = k[:, None] * (rotation @ table[:, 0:3, None])[..., 0] + centre
    quats = quaternion_multiply(frames.quaternion[face], table[:, [7, 4, 5, 6]])  # w x y z
    shading = torch.stack([table[:, 16:19], torch.cat([table[:, 19:20], table[:, 20:22]], 1),
                           torch.cat([table[:, 22:24], table[:, 15:16]], 1)], 1)  # [N, 3, 3] rows of F
    colours = (table[:, 12:15] + (shading @ rotation[:, :, 1:2])[..., 0]).clamp_min(0)
    np.testing.assert_allclose(means, expected.means.double(), atol=1e-6)
    np.testing.assert_allclose(quaternion_to_matrix(quats), quaternion_to_matrix(expected.quats.double()), atol=1e-5)
    np.testing.assert_allclose(k[:, None] * table[:, 8:11], expected.scales.double(), rtol=1e-5)
    np.testing.assert_allclose(table[:, 11], expected.opacities.double(), rtol=1e-6)
    np.testing.assert_allclose(colours, expected.colors.double(), atol=1e-5)
