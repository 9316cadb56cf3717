"""avatar/fused.py: the hand-written backwards of local -> global and the polar coordinates against
autograd of the plain PyTorch ops (the code they replaced) and finite differences (gradcheck)."""

import pytest
import torch
import torch.nn.functional as F

from geoavatar.avatar import face_frames, local_to_global
from geoavatar.avatar.fused import native_loops_available, place_gaussians, polar_coordinates as fused_polar
from geoavatar.geometry import quaternion_multiply


def plain_local_to_global(means, quats, log_scales, binding, frames):
    """The plain-op version of binding.local_to_global (the reference)."""
    rot = frames.rotation[..., binding, :, :]
    k = frames.scale[..., binding, None]
    means_g = k * (rot @ means[..., None]).squeeze(-1) + frames.centre[..., binding, :]
    face_quat = frames.quaternion[..., binding, :]
    quats_g = quaternion_multiply(face_quat, F.normalize(quats, dim=-1).expand_as(face_quat))
    return means_g, quats_g, k * torch.exp(log_scales)


def plain_polar(mu, two_sided=False, axis=1):
    r = torch.linalg.vector_norm(mu, dim=-1)
    tiny = r <= 1e-12
    along = torch.zeros_like(mu)
    along[..., axis] = 1.0
    safe = torch.where(tiny[..., None], along, mu)
    normal = safe[..., axis].abs() if two_sided else safe[..., axis]
    others = [a for a in range(3) if a != axis]
    return r, torch.atan2(torch.linalg.vector_norm(safe[..., others], dim=-1), normal)


def sheet(dtype, batch=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = 4
    ys, xs = torch.meshgrid(torch.arange(n, dtype=dtype), torch.arange(n, dtype=dtype), indexing="ij")
    verts = torch.stack([xs.reshape(-1), ys.reshape(-1), 0.3 * torch.randn(n * n, generator=g, dtype=dtype)], -1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    if batch:
        verts = torch.stack([verts * (1.0 + 0.5 * i) + 0.1 * i for i in range(batch)])
    return verts, torch.tensor(faces)


def gaussians(num_faces, per_face, dtype, seed=1):
    g = torch.Generator().manual_seed(seed)
    n = num_faces * per_face
    binding = torch.arange(num_faces).repeat(per_face)[torch.randperm(n, generator=g)]
    return (torch.randn(n, 3, generator=g, dtype=dtype), torch.randn(n, 4, generator=g, dtype=dtype),
            0.3 * torch.randn(n, 3, generator=g, dtype=dtype), binding)


@pytest.mark.parametrize("batch", [None, 2])
def test_place_gaussians_matches_plain_ops_values_and_gradients(batch):
    verts, faces = sheet(torch.float32, batch)
    means, quats, log_scales, binding = gaussians(len(faces), 3, torch.float32)
    quats[0] = 0.0  # a zero quaternion: normalize's clamped branch (gradient g / eps)
    grads = {}
    for name, fn in (("fused", local_to_global), ("plain", plain_local_to_global)):
        leaves = [t.clone().requires_grad_() for t in (verts, means, quats, log_scales)]
        out = fn(*leaves[1:], binding, face_frames(leaves[0], faces))
        weights = [torch.randn(o.shape, generator=torch.Generator().manual_seed(i)) for i, o in enumerate(out)]
        sum((o * w).sum() for o, w in zip(out, weights)).backward()
        grads[name] = (out, [leaf.grad for leaf in leaves])
    for a, b in zip(grads["fused"][0], grads["plain"][0]):
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-6, rtol=1e-5)
    for a, b in zip(grads["fused"][1], grads["plain"][1]):
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)


def _native_or_skip(native):
    if native and not native_loops_available():
        pytest.skip("the native CPU extension is not available")


@pytest.mark.parametrize("native", [False, True])
def test_place_gaussians_gradcheck(native):
    _native_or_skip(native)
    verts, faces = sheet(torch.float64)
    frames = face_frames(verts, faces)
    means, quats, log_scales, binding = gaussians(len(faces), 2, torch.float64)
    inputs = [t.clone().requires_grad_() for t in (frames.rotation, frames.centre, frames.scale, frames.quaternion,
                                                   means, quats, log_scales)]
    assert torch.autograd.gradcheck(lambda *x: place_gaussians(*x, binding, native=native), inputs)


@pytest.mark.parametrize("batch", [None, 2])
def test_native_placement_matches_the_torch_function(batch):
    """The native loops (avatar/csrc) against _PlaceGaussians: the same maths, float rounding apart."""
    _native_or_skip(True)
    verts, faces = sheet(torch.float32, batch)
    frames = face_frames(verts, faces)
    means, quats, log_scales, binding = gaussians(len(faces), 3, torch.float32)
    quats[0] = 0.0
    results = {}
    for native in (False, True):
        leaves = [t.detach().clone().requires_grad_() for t in (frames.rotation, frames.centre, frames.scale,
                                                                frames.quaternion, means, quats, log_scales)]
        out = place_gaussians(*leaves, binding, native=native)
        weights = [torch.randn(o.shape, generator=torch.Generator().manual_seed(i)) for i, o in enumerate(out)]
        sum((o * w).sum() for o, w in zip(out, weights)).backward()
        results[native] = (out, [leaf.grad for leaf in leaves])
    for a, b in zip(results[True][0], results[False][0]):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    for a, b in zip(results[True][1], results[False][1]):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("native", [False, True])
@pytest.mark.parametrize("two_sided", [False, True])
def test_polar_coordinates_match_plain_ops_and_gradcheck(two_sided, native):
    _native_or_skip(native)
    g = torch.Generator().manual_seed(3)
    mu = torch.randn(40, 3, generator=g, dtype=torch.float64)
    mu[0] = 0.0  # the origin: phi = 0, no gradient
    mu[1] = torch.tensor([0.0, 2.0, 0.0])  # on the normal: tangent norm 0
    mu[2] = torch.tensor([0.0, -1.5, 0.0])
    mu[3] = torch.tensor([0.7, 0.0, -0.2])  # in the face plane
    leaves = [mu.clone().requires_grad_() for _ in range(2)]
    (r, phi), (r0, phi0) = (fused_polar(leaves[0], two_sided, native=native),
                            plain_polar(leaves[1], two_sided))
    assert torch.allclose(r, r0) and torch.allclose(phi, phi0)
    w = torch.randn(2, 40, generator=g, dtype=torch.float64)
    ((r * w[0]).sum() + (phi * w[1]).sum()).backward()
    ((r0 * w[0]).sum() + (phi0 * w[1]).sum()).backward()
    assert torch.allclose(leaves[0].grad, leaves[1].grad)
    smooth = mu[4:].clone().requires_grad_()  # away from the kinks, finite differences hold
    assert torch.autograd.gradcheck(lambda x: fused_polar(x, two_sided, native=native), [smooth])
