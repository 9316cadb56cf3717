"""Mesh rasterizer (geoavatar.render.mesh) and camera helpers (geoavatar.render.camera)."""

import math

import numpy as np
import pytest
import torch

from geoavatar.geometry import camera_centre
from geoavatar.render.camera import (
    fov_from_intrinsics, intrinsics_from_fov, look_at, opengl_c2w_to_viewmat, project,
    viewmat_to_opengl_c2w, world_to_camera,
)
from geoavatar.render import mesh as mesh_module
from geoavatar.render.mesh import (
    Lighting, behind_surface, box_downsample, face_attribute, interpolate, rasterize_mesh, render_mesh, shade,
    vertex_normals,
)

W, H = 64, 48
K = torch.tensor([[60.0, 0.0, W / 2], [0.0, 60.0, H / 2], [0.0, 0.0, 1.0]])


def unproject(px: float, py: float, z: float) -> list[float]:
    """Camera point at depth z seen at pixel position (px, py)."""
    return [(px - K[0, 2].item()) / K[0, 0].item() * z, (py - K[1, 2].item()) / K[1, 1].item() * z, z]


def pixel_centres() -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    return xs, ys


def test_single_triangle_coverage_matches_point_in_triangle():
    tri_px = np.array([[5.3, 4.1], [57.7, 12.6], [20.2, 44.9]])
    verts = torch.tensor([unproject(x, y, 2.0) for x, y in tri_px], dtype=torch.float32)
    frags = rasterize_mesh(verts, torch.tensor([[0, 1, 2]]), K, W, H)

    xs, ys = pixel_centres()
    edge_values = []
    for i in range(3):
        (ax, ay), (bx, by) = tri_px[i], tri_px[(i + 1) % 3]
        edge_values.append((bx - ax) * (ys - ay) - (by - ay) * (xs - ax))
    edge_values = np.stack(edge_values)  # [3, H, W]
    inside = (edge_values >= 0).all(0) | (edge_values <= 0).all(0)
    near_edge = (np.abs(edge_values) < 1e-3).any(0)
    got = frags.mask.numpy()
    assert inside.sum() > 300
    assert np.array_equal(got[~near_edge], inside[~near_edge])
    assert (frags.face_id[frags.mask] == 0).all()
    assert torch.isinf(frags.depth[~frags.mask]).all()
    assert torch.allclose(frags.depth[frags.mask], torch.tensor(2.0), atol=1e-5)
    assert torch.allclose(frags.bary[frags.mask].sum(-1), torch.tensor(1.0), atol=1e-5)


def quad(z: float, x0=8.0, y0=6.0, x1=56.0, y1=42.0) -> list[list[float]]:
    return [unproject(x0, y0, z), unproject(x1, y0, z), unproject(x1, y1, z), unproject(x0, y1, z)]


def test_near_triangle_wins_whatever_the_order():
    verts = torch.tensor(quad(3.0) + quad(1.5, 20, 15, 40, 30), dtype=torch.float32)
    far, near = [[0, 1, 2], [0, 2, 3]], [[4, 5, 6], [4, 6, 7]]
    for faces, near_ids in (([*far, *near], (2, 3)), ([*near, *far], (0, 1))):
        frags = rasterize_mesh(verts, torch.tensor(faces), K, W, H)
        centre = frags.face_id[22, 30].item()
        assert centre in near_ids
        assert frags.depth[22, 30].item() == pytest.approx(1.5, rel=1e-5)
        assert frags.depth[8, 10].item() == pytest.approx(3.0, rel=1e-5)  # only the far quad there


def test_equal_depth_ties_go_to_the_smaller_face_id():
    verts = torch.tensor(quad(2.0), dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 3]])
    frags = rasterize_mesh(verts, faces, K, W, H)
    assert set(frags.face_id[frags.mask].unique().tolist()) == {0, 1}


def slanted_plane() -> tuple[torch.Tensor, torch.Tensor]:
    """A quad receding from z=1 (left) to z=4 (right), filling most of the image."""
    left, right = 1.0, 4.0
    verts = torch.tensor(
        [unproject(2, 2, left), unproject(62, 2, right), unproject(62, 46, right), unproject(2, 46, left)],
        dtype=torch.float32,
    )
    return verts, torch.tensor([[0, 1, 2], [0, 2, 3]])


def test_linear_attributes_are_interpolated_exactly():
    verts, faces = slanted_plane()
    frags = rasterize_mesh(verts, faces, K, W, H)
    mask = frags.mask
    assert mask.float().mean() > 0.7
    # An attribute affine in 3D, and the 3D positions themselves: exact at every covered pixel.
    weights = torch.tensor([[0.3, -1.2], [2.0, 0.5], [-0.7, 0.25]])
    attr = verts @ weights + torch.tensor([0.1, -0.4])  # [V, 2]
    positions = interpolate(frags, verts, faces)  # [H, W, 3]
    expected = positions @ weights + torch.tensor([0.1, -0.4])
    assert torch.allclose(interpolate(frags, attr, faces)[mask], expected[mask], atol=1e-4)
    # Each interpolated position lies on its pixel's ray: it projects back to the pixel centre.
    xs, ys = pixel_centres()
    uvw = positions[mask] @ K.T
    assert torch.allclose(uvw[:, 0] / uvw[:, 2], torch.from_numpy(xs[mask.numpy()]).float(), atol=1e-3)
    assert torch.allclose(uvw[:, 1] / uvw[:, 2], torch.from_numpy(ys[mask.numpy()]).float(), atol=1e-3)
    assert (interpolate(frags, attr, faces, background=7.0)[~mask] == 7.0).all()


def test_depth_on_a_slanted_plane_is_perspective_correct():
    verts, faces = slanted_plane()
    frags = rasterize_mesh(verts, faces, K, W, H)
    mask = frags.mask
    # The plane z = a*x_cam + c through the quad: intersect each pixel ray analytically.
    (xa, _, za), (xb, _, zb) = verts[0].tolist(), verts[1].tolist()
    slope = (zb - za) / (xb - xa)
    xs, _ = pixel_centres()
    ray_x = (torch.from_numpy(xs).float() - K[0, 2]) / K[0, 0]  # x_cam / z along each ray
    analytic = (za - slope * xa) / (1.0 - slope * ray_x)  # [H, W]
    assert torch.allclose(frags.depth[mask], analytic[mask], rtol=1e-4)
    interpolated_z = interpolate(frags, verts[:, 2:], faces)[..., 0]
    assert torch.allclose(interpolated_z[mask], analytic[mask], rtol=1e-4)
    # Screen-space (non-perspective) interpolation is far off: the test can tell the two apart.
    screen_linear = za + (zb - za) * (torch.from_numpy(xs).float() - 2.0) / 60.0
    assert (screen_linear[mask] - analytic[mask]).abs().max() > 0.5


def test_empty_scenes():
    faces = torch.tensor([[0, 1, 2]])
    cases = {
        "no faces": (torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.int64)),
        "behind the camera": (torch.tensor(quad(-2.0)[:3], dtype=torch.float32), faces),
        "outside the image": (torch.tensor([unproject(-30, -20, 2), unproject(-5, -20, 2), unproject(-5, -2, 2)]), faces),
        "degenerate": (torch.tensor([unproject(3, 3, 2), unproject(20, 20, 2), unproject(40, 40, 2)]), faces),
    }
    for name, (verts, f) in cases.items():
        frags = rasterize_mesh(verts, f, K, W, H)
        assert not frags.mask.any(), name
        assert frags.face_id.shape == (H, W) and frags.bary.shape == (H, W, 3), name
        assert torch.isinf(frags.depth).all(), name
        assert (interpolate(frags, torch.ones(verts.shape[0], 2), f) == 0).all(), name


def test_triangles_crossing_the_near_plane_are_dropped():
    verts = torch.tensor([unproject(10, 10, 2.0), unproject(50, 10, 2.0), [0.0, 0.5, -0.5]])
    assert not rasterize_mesh(verts, torch.tensor([[0, 1, 2]]), K, W, H).mask.any()


def test_backface_culling_keeps_faces_whose_normal_points_at_the_camera():
    verts = torch.tensor(quad(2.0), dtype=torch.float32)
    survivors = []
    for faces in ([[0, 1, 2]], [[0, 2, 1]]):  # the two windings of one triangle
        f = torch.tensor(faces)
        tri = verts[f[0]]
        towards_camera = bool(torch.dot(torch.linalg.cross(tri[1] - tri[0], tri[2] - tri[0]), tri[0]) < 0)
        kept = rasterize_mesh(verts, f, K, W, H, cull_backfaces=True).mask.any().item()
        assert kept == towards_camera
        assert rasterize_mesh(verts, f, K, W, H, cull_backfaces=False).mask.any()
        survivors.append(kept)
    assert survivors in ([True, False], [False, True])


def random_triangles(count: int, seed: int, spread: float = 40.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Overlapping triangles of random sizes and depths over the image: vertices [3 count, 3], faces [count, 3]."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(count, 1, 2, generator=g) * torch.tensor([W, H])
    corners = centres + (torch.rand(count, 3, 2, generator=g) - 0.5) * spread  # [count, 3, 2]
    depths = 1.0 + torch.rand(count, 3, 1, generator=g) * 3
    verts = torch.tensor(
        [unproject(x, y, z) for (x, y), z in zip(corners.reshape(-1, 2).tolist(), depths.reshape(-1).tolist())]
    )
    return verts, torch.arange(3 * count).reshape(count, 3)


@pytest.fixture
def torch_scan(monkeypatch):
    """rasterize_mesh with its PyTorch scan, as on CUDA or without a compiler (the CPU's is native)."""
    monkeypatch.setattr(mesh_module, "_native_kernels", lambda: None)


def test_the_native_scan_writes_the_torch_scans_fragments(monkeypatch):
    """The CPU's native z-buffer and the PyTorch one agree bit for bit, on a triangle soup and on a turned head."""
    if mesh_module._native_kernels() is None:
        pytest.skip("the native kernels cannot be built here")
    from geoavatar.head import load_head_model

    head = load_head_model("openhead")
    turn = torch.tensor([[0.94, 0.0, 0.34], [0.0, 1.0, 0.0], [-0.34, 0.0, 0.94]])
    head_cam = head.v_template.float() @ turn.T + torch.tensor([0.0, 0.02, 0.6])
    K_head = torch.tensor([[250.0, 0.0, 64.0], [0.0, 250.0, 64.0], [0.0, 0.0, 1.0]])
    soup = random_triangles(200, seed=1)
    cases = [(*soup, K, W, H, False), (head_cam, head.faces, K_head, 128, 128, False),
             (head_cam, head.faces, K_head, 128, 128, True)]
    for verts, faces, intrinsics, width, height, cull in cases:
        native = rasterize_mesh(verts, faces, intrinsics, width, height, cull_backfaces=cull)
        with monkeypatch.context() as patch:
            patch.setattr(mesh_module, "_native_kernels", lambda: None)
            scanned = rasterize_mesh(verts, faces, intrinsics, width, height, cull_backfaces=cull)
        assert native.mask.sum() > 1000
        assert torch.equal(native.face_id, scanned.face_id)
        assert torch.equal(native.depth, scanned.depth)
        assert torch.equal(native.bary, scanned.bary)


def test_chunking_and_splitting_do_not_change_the_result(torch_scan):
    g = torch.Generator().manual_seed(0)
    centres = torch.rand(60, 1, 2, generator=g) * torch.tensor([W, H])
    corners = centres + (torch.rand(60, 3, 2, generator=g) - 0.5) * 40  # [60, 3, 2] overlapping triangles
    depths = 1.0 + torch.rand(60, 3, 1, generator=g) * 3
    verts = torch.tensor(
        [unproject(x, y, z) for (x, y), z in zip(corners.reshape(-1, 2).tolist(), depths.reshape(-1).tolist())]
    )
    faces = torch.arange(180).reshape(60, 3)
    reference = rasterize_mesh(verts, faces, K, W, H)
    small = rasterize_mesh(verts, faces, K, W, H, chunk_candidates=257, piece_pixels=40)
    assert reference.mask.sum() > 1000
    assert torch.equal(reference.face_id, small.face_id)
    assert torch.equal(reference.depth, small.depth)
    assert torch.allclose(reference.bary, small.bary)
    # Every covered pixel shows the minimum depth over the triangles that contain its centre.
    shuffled = torch.randperm(60, generator=g)
    again = rasterize_mesh(verts, faces[shuffled], K, W, H)
    assert torch.equal(again.depth, reference.depth)


def test_supersampled_mask_is_fractional_on_edges():
    tri_px = [[6.0, 5.0], [58.0, 9.0], [15.0, 43.0]]
    verts = torch.tensor([unproject(x, y, 2.0) for x, y in tri_px], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2]])
    out = render_mesh(verts, faces, torch.eye(4), K, W, H, ssaa=4, lighting=None,
                      vertex_colors=torch.tensor([[1.0, 0, 0]] * 3), background=(0.0, 0.0, 1.0))
    mask = out.mask
    assert mask.shape == (H, W) and out.image.shape == (H, W, 3)
    fractional = (mask > 0.05) & (mask < 0.95)
    assert fractional.sum() > 40  # the three edges
    assert (mask == 1).sum() > 500 and (mask == 0).sum() > 500
    area = 0.5 * abs((58 - 6) * (43 - 5) - (15 - 6) * (9 - 5))
    assert mask.sum().item() == pytest.approx(area, rel=0.03)
    # Colour is composited with the same coverage: red = mask, blue = 1 - mask.
    assert torch.allclose(out.image[..., 0], mask, atol=1e-6)
    assert torch.allclose(out.image[..., 2], 1 - mask, atol=1e-6)


def test_face_attribute_normals_and_shading():
    verts = torch.tensor(quad(2.0), dtype=torch.float32)
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])  # normal towards the camera (-z)
    normals = vertex_normals(verts, faces)
    assert torch.allclose(normals, torch.tensor([0.0, 0.0, -1.0]).expand(4, 3), atol=1e-6)
    frags = rasterize_mesh(verts, faces, K, W, H)
    labels = face_attribute(frags, torch.tensor([[1.0], [2.0]]), background=-1.0)[..., 0]
    assert set(labels.unique().tolist()) == {-1.0, 1.0, 2.0}
    albedo = torch.full((2, 3), 0.5)
    facing = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    lit = shade(albedo, facing, lighting=Lighting(two_sided=True))
    assert torch.allclose(lit[0], lit[1])  # two-sided: the back face is lit like the front
    one_sided = shade(albedo, facing, lighting=Lighting(two_sided=False))
    assert (one_sided[1] < one_sided[0]).all()
    assert torch.allclose(one_sided[1], torch.full((3,), 0.5 * Lighting().ambient))


def test_box_downsample():
    x = torch.arange(16.0).reshape(4, 4)
    assert torch.equal(box_downsample(x, 2), torch.tensor([[2.5, 4.5], [10.5, 12.5]]))
    with pytest.raises(ValueError):
        box_downsample(torch.zeros(5, 4, 3), 2)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="vertices_cam"):
        rasterize_mesh(torch.zeros(3, 2), torch.tensor([[0, 1, 2]]), K, W, H)
    with pytest.raises(ValueError, match="faces index"):
        rasterize_mesh(torch.zeros(3, 3), torch.tensor([[0, 1, 3]]), K, W, H)


# --- camera ------------------------------------------------------------------------------------


def test_point_in_front_of_the_camera_projects_to_the_principal_point():
    eye = torch.tensor([0.3, 0.2, 1.5])
    target = torch.tensor([0.0, 0.05, 0.0])
    viewmat = look_at(eye, target)
    K_fov = intrinsics_from_fov(30.0, 128, 96)
    pixels, depth = project(target[None], viewmat, K_fov)
    assert torch.allclose(pixels[0], torch.tensor([64.0, 48.0]), atol=1e-4)
    assert depth[0].item() == pytest.approx((eye - target).norm().item(), rel=1e-5)
    assert fov_from_intrinsics(K_fov, 128, 96) == pytest.approx(30.0)


def test_look_at_uses_opencv_axes():
    viewmat = look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])  # in front of the face
    cam = world_to_camera(torch.tensor([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.0]]), viewmat)
    assert cam[0, 0] > 0  # the subject's left (+x) is on the image right
    assert cam[1, 1] < 0  # world up is image up (camera +y points down)
    assert cam[2, 2].item() == pytest.approx(1.0)  # forward
    rot = viewmat[:3, :3]
    assert torch.allclose(rot @ rot.T, torch.eye(3), atol=1e-6) and torch.det(rot).item() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="up"):
        look_at([0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_opengl_camera_to_world_round_trip():
    g = torch.Generator().manual_seed(3)
    eyes = torch.randn(5, 3, generator=g) + torch.tensor([0.0, 0.0, 2.0])
    viewmats = look_at(eyes, torch.zeros(5, 3), torch.tensor([0.0, 1.0, 0.0]))  # [5, 4, 4]
    c2w = viewmat_to_opengl_c2w(viewmats)
    assert torch.allclose(opengl_c2w_to_viewmat(c2w), viewmats, atol=1e-5)
    assert torch.allclose(opengl_c2w_to_viewmat(c2w[:, :3]), viewmats, atol=1e-5)  # [3, 4] accepted
    # OpenGL: the camera centre is the translation, and it looks down its -z axis at the target.
    assert torch.allclose(c2w[:, :3, 3], eyes, atol=1e-5)
    look_dir = -c2w[:, :3, 2]
    assert torch.allclose(look_dir, torch.nn.functional.normalize(-eyes, dim=-1), atol=1e-5)
    assert torch.allclose(c2w[:, :3, 1] @ torch.tensor([0.0, 1.0, 0.0]) > 0, torch.ones(5, dtype=torch.bool))
    with pytest.raises(ValueError, match="c2w_gl"):
        opengl_c2w_to_viewmat(torch.eye(3))


def test_intrinsics_from_fov_axis():
    K_x = intrinsics_from_fov(90.0, 200, 100)
    assert K_x[0, 0].item() == pytest.approx(100.0)
    K_y = intrinsics_from_fov(90.0, 200, 100, axis="y")
    assert K_y[1, 1].item() == pytest.approx(50.0)
    assert K_y[0, 2].item() == 100.0 and K_y[1, 2].item() == 50.0
    with pytest.raises(ValueError, match="fov_deg"):
        intrinsics_from_fov(180.0, 10, 10)
    assert math.isclose(fov_from_intrinsics(K_y, 200, 100, axis="y"), 90.0)


def test_camera_centre_is_the_eye_of_each_viewmat():
    eyes = torch.tensor([[0.1, 0.2, 1.5], [-2.0, 0.5, 0.3], [0.0, -1.0, -3.0]], dtype=torch.float64)  # [3, 3]
    viewmats = look_at(eyes, torch.zeros(3, dtype=torch.float64))  # [3, 4, 4]
    torch.testing.assert_close(camera_centre(viewmats), eyes)
    torch.testing.assert_close(camera_centre(viewmats[1]), eyes[1])  # one matrix: [3]


def test_behind_surface_tests_each_point_against_the_depth_where_it_projects():
    depth = torch.full((4, 4), float("inf"))
    depth[:, :2] = 1.0  # the left half is covered at z = 1
    K = torch.tensor([[2.0, 0.0, 2.0], [0.0, 2.0, 2.0], [0.0, 0.0, 1.0]])
    points = torch.tensor([
        [-0.5, 0.0, 1.0],    # on the surface
        [-0.5, 0.0, 1.004],  # within the margin
        [-0.5, 0.0, 1.05],   # behind it
        [0.5, 0.0, 1.05],    # behind, but over an uncovered pixel
        [-5.0, 0.0, 1.05],   # off the image
        [-0.5, 0.0, -1.0],   # behind the camera
    ])
    assert behind_surface(points, depth, K, 0.005).tolist() == [False, False, True, False, False, False]
