"""Renderer: cameras, mesh visibility vs ray casting and the pure-torch reference, gradients,
point splatting vs reference and an analytic sphere, shading, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from headforge.render import kernels, mesh, points, shading
from headforge.render.camera import Cameras, look_at_head
from headforge.render.raycast import raycast


def _cams(res=64, distance=0.5, yaw=0.0, dtype=torch.float64, B=1):
    return Cameras.from_pinhole([look_at_head(res, res, distance=distance, yaw_deg=yaw + 7 * i) for i in range(B)], dtype=dtype)


def _sphere(subdivisions=3, radius=0.1):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.tensor(s.vertices)[None], torch.tensor(s.faces)


# ---- cameras -------------------------------------------------------------------------------
def test_camera_projection_matches_numpy_and_converters_round_trip():
    pin = look_at_head(96, 80, distance=0.7, yaw_deg=20, pitch_deg=-5)
    cams = Cameras.from_pinhole([pin], dtype=torch.float64)
    pts = torch.randn(1, 50, 3, dtype=torch.float64) * 0.1
    np.testing.assert_allclose(cams.project(pts)[0, :, :2].numpy(), pin.project(pts[0].numpy()), atol=1e-9)
    back = Cameras.from_opengl_c2w(cams.to_opengl_c2w(), cams.K, 96, 80)
    torch.testing.assert_close(back.R, cams.R)
    torch.testing.assert_close(back.t, cams.t)
    again = Cameras.from_nerf_transforms(cams.to_nerf_transforms())
    torch.testing.assert_close(again.project(pts), cams.project(pts))
    c2w = cams.to_opengl_c2w()[0]
    # OpenGL camera looks down its -z axis: toward the head at the origin
    toward = -c2w[:3, 2]
    torch.testing.assert_close(toward, -c2w[:3, 3] / c2w[:3, 3].norm())


def test_bad_cameras():
    with pytest.raises(ValueError, match="image size must be positive"):
        Cameras(torch.eye(3)[None], torch.eye(3)[None], torch.zeros(1, 3), 0, 10)
    with pytest.raises(ValueError, match="Cameras need"):
        Cameras(torch.eye(3), torch.eye(3)[None], torch.zeros(1, 3), 10, 10)


# ---- mesh visibility -----------------------------------------------------------------------
def test_rasterizer_matches_ray_casting_on_the_head(open_head):
    verts = open_head(jaw_pose=torch.tensor([[0.15, 0, 0]])).vertices.double()
    for yaw in (0.0, 35.0):
        pin = look_at_head(160, 160, distance=0.6, yaw_deg=yaw)
        frags = mesh.rasterize(Cameras.from_pinhole([pin], torch.float64), verts, open_head.faces)
        hits = raycast(verts[0].numpy(), open_head.faces.numpy(), pin)
        covered = hits.mask | frags.mask[0].numpy()
        agreement = (hits.face_id == frags.face_id[0].numpy())[covered].mean()
        assert agreement >= 0.995, agreement


def test_numba_rasterizer_equals_torch_reference():
    v, f = _sphere(2)
    extra = torch.tensor([[[-0.05, -0.05, 0.05], [0.08, -0.02, 0.12], [0.0, 0.09, 0.02]]], dtype=torch.float64)
    v = torch.cat([v, extra], 1)  # a triangle that cuts through the sphere
    f = torch.cat([f, torch.tensor([[v.shape[1] - 3, v.shape[1] - 2, v.shape[1] - 1]])])
    cams = _cams(48, B=2)
    xyz = cams.project(v.expand(2, -1, -1))
    ref = kernels.rasterize_reference(xyz, f, 48, 48)
    fast = kernels.rasterize_numba(xyz.numpy(), f.numpy(), 48, 48)
    same = ref[0].numpy() == fast[0]
    assert same.mean() > 0.998  # only exact ties on shared edges may differ
    both = (ref[0].numpy() >= 0) & (fast[0] >= 0)
    np.testing.assert_allclose(ref[2].numpy()[both], fast[2][both], atol=1e-9)


@pytest.mark.parametrize("chunk_pairs", [1 << 22, 997])
def test_torch_rasterizer_equals_numba_kernel_bit_for_bit(chunk_pairs):
    """The CUDA path's vectorised z-buffer against the numba kernel: same faces, barycentrics
    and depths (same float64 arithmetic), also when the pairs are cut into many chunks and with
    NaN, behind-the-camera, degenerate and off-screen triangles in the batch."""
    v, f = _sphere(3)
    extra = torch.tensor([[[-0.05, -0.05, 0.05], [0.08, -0.02, 0.12], [0.0, 0.09, 0.02],  # cuts the sphere
                           [float("nan"), 0, 0], [0, 0, 1.0], [0.01, 0.0, 0.0],  # NaN vertex
                           [0, 0, 0.6], [0.01, 0, 0.6], [0, 0.01, 0.6],  # behind the camera (distance 0.5)
                           [0, 0, 0], [0.01, 0.01, 0], [0.02, 0.02, 0],  # degenerate
                           [5, 5, 0], [5.1, 5, 0], [5, 5.1, 0]]], dtype=torch.float64)  # off-screen
    n = v.shape[1]
    v = torch.cat([v, extra], 1)
    f = torch.cat([f, torch.arange(n, n + 15).reshape(5, 3)])
    cams = _cams(40, B=3)
    xyz = cams.project(v.expand(3, -1, -1))
    fast = kernels.rasterize_numba(xyz.numpy(), f.numpy(), 40, 40)
    vec = kernels.rasterize_torch(xyz, f, 40, 40, chunk_pairs=chunk_pairs)
    np.testing.assert_array_equal(vec[0].numpy(), fast[0])
    np.testing.assert_array_equal(vec[1].numpy(), fast[1])
    np.testing.assert_array_equal(vec[2].numpy(), fast[2])
    assert (fast[0] == len(f) - 5).any() and not np.isin(fast[0], np.arange(len(f) - 4, len(f))).any()
    via_mesh = mesh.rasterize(cams, v.expand(3, -1, -1), f, backend="torch")
    np.testing.assert_array_equal(via_mesh.face_id.numpy(), fast[0])
    assert mesh.rasterize(cams, v.expand(3, -1, -1), torch.zeros(0, 3, dtype=torch.long), backend="torch").face_id.eq(-1).all()


def test_differentiable_barycentrics_equal_the_rasterizer():
    v, f = _sphere(3)
    cams = _cams(64)
    frags = mesh.rasterize(cams, v, f)
    torch.testing.assert_close(mesh.barycentrics(frags, cams, v, f), frags.bary, atol=1e-9, rtol=0)
    some = frags.mask & (torch.rand(frags.mask.shape) < 0.3)  # a subset of the covered pixels
    torch.testing.assert_close(mesh.barycentrics(frags, cams, v, f, pixels=some), frags.bary[some], atol=1e-9, rtol=0)


def test_interpolation_gradcheck():
    v, f = _sphere(1)
    cams = _cams(24)
    frags = mesh.rasterize(cams, v, f)
    attr = torch.randn(v.shape[1], 2, dtype=torch.float64)

    def render(verts, attributes):
        bary = mesh.barycentrics(frags, cams, verts, f)
        return mesh.interpolate(attributes, frags, f, bary)

    assert torch.autograd.gradcheck(render, (v.clone().requires_grad_(), attr.requires_grad_()), eps=1e-7, atol=1e-5)


def test_per_corner_attributes_and_texture():
    v, f = _sphere(2)
    cams = _cams(48)
    frags = mesh.rasterize(cams, v, f)
    uv_corner = torch.rand(f.shape[0], 3, 2, dtype=torch.float64)
    uv = mesh.interpolate(uv_corner, frags, f, per_corner=True)
    # per-corner with identical corners equals per-vertex
    per_vertex = torch.rand(v.shape[1], 2, dtype=torch.float64)
    torch.testing.assert_close(mesh.interpolate(per_vertex[f], frags, f, per_corner=True),
                               mesh.interpolate(per_vertex, frags, f))
    # a linear ramp texture returns the u coordinate (bilinear is exact on linear data)
    tex = ((torch.arange(64, dtype=torch.float64) + 0.5) / 64)[None, None, :, None].expand(1, 64, 64, 1)
    out = mesh.texture(uv, tex, frags.mask)
    inside = frags.mask & (uv[..., 0] > 1 / 64) & (uv[..., 0] < 1 - 1 / 64)
    torch.testing.assert_close(out[..., 0][inside], uv[..., 0][inside], atol=1e-6, rtol=0)


def test_antialias_silhouette_gradient_matches_finite_differences():
    # one large triangle in front of the camera, edges at non-integer positions
    v = torch.tensor([[[-0.031, -0.027, 0.0], [0.036, -0.019, 0.0], [0.004, 0.033, 0.0]]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2]])
    cams = _cams(32)
    frags = mesh.rasterize(cams, v, f)
    weights = torch.rand(1, 32, 32, 1, dtype=torch.float64)

    def soft_mask(verts):
        m = frags.mask[..., None].to(verts.dtype)
        return (mesh.antialias(m, frags, cams, verts, f) * weights).sum()

    verts = v.clone().requires_grad_()
    soft_mask(verts).backward()
    assert verts.grad.abs().sum() > 0
    assert torch.autograd.gradcheck(soft_mask, (v.clone().requires_grad_(),), eps=1e-7, atol=1e-5)
    # area check: the antialiased mask sums to about the projected triangle area
    xy = cams.project(v)[0, :, :2]
    area = 0.5 * abs(float((xy[1, 0] - xy[0, 0]) * (xy[2, 1] - xy[0, 1]) - (xy[2, 0] - xy[0, 0]) * (xy[1, 1] - xy[0, 1])))
    aa_sum = mesh.antialias(frags.mask[..., None].double(), frags, cams, v, f).sum().item()
    assert abs(aa_sum - area) < abs(frags.mask.sum().item() - area) + 1e-9
    assert abs(aa_sum - area) / area < 0.03


def test_mesh_bad_input_is_handled():
    v, f = _sphere(1)
    cams = _cams(32)
    empty = mesh.rasterize(cams, v, torch.zeros(0, 3, dtype=torch.long))
    assert not empty.mask.any()
    nan = v.clone()
    nan[0, :5] = float("nan")
    frags = mesh.rasterize(cams, nan, f)
    assert frags.mask.any() and torch.isfinite(frags.depth[frags.mask]).all()
    behind = v.clone()
    behind[..., 2] += 0.6  # the whole mesh behind the camera (camera at z = 0.5 looking to -z)
    assert not mesh.rasterize(cams, behind, f).mask.any()
    degenerate = torch.zeros(1, 3, 3, dtype=torch.float64)
    assert not mesh.rasterize(cams, degenerate, torch.tensor([[0, 1, 2]])).mask.any()
    with pytest.raises(ValueError, match="vertices must be"):
        mesh.rasterize(cams, v[0], f)
    with pytest.raises(ValueError, match="faces index outside"):
        mesh.rasterize(cams, v, f + 1000)
    with pytest.raises(ValueError, match="1 meshes but 2 cameras"):
        mesh.rasterize(_cams(32, B=2), v, f)
    # NaN vertices: no NaN gradients anywhere (they are invisible, their gradient is zero)
    vv = nan.clone().requires_grad_()
    frags = mesh.rasterize(cams, vv, f)
    image = mesh.interpolate(torch.ones(v.shape[1], 1, dtype=torch.float64), frags, f, mesh.barycentrics(frags, cams, vv, f))
    mesh.antialias(torch.cat([image, frags.mask[..., None].double()], -1), frags, cams, vv, f).sum().backward()
    assert torch.isfinite(vv.grad).all() and vv.grad[0, :5].abs().sum() == 0


# ---- points --------------------------------------------------------------------------------
def test_numba_splat_equals_torch_reference():
    gen = torch.Generator().manual_seed(0)
    pts = (torch.rand(2, 400, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.15
    cams = _cams(40, B=2)
    xyz = cams.project(pts)
    radius = 0.5 + 2 * torch.rand(2, 400, generator=gen, dtype=torch.float64)
    ref_idx, ref_depth = kernels.splat_reference(xyz, radius, 40, 40, 5)
    idx, depth = kernels.splat_numba(xyz.numpy(), radius.numpy(), 40, 40, 5)
    np.testing.assert_array_equal(ref_idx.numpy(), idx)
    np.testing.assert_allclose(ref_depth.numpy(), depth)


def _awkward_cloud(B, N, res, gen):
    """Projected random points (continuous depths) with per-point radii, plus points off-screen,
    behind the camera, NaN, with zero radius and covering the image border."""
    pts = (torch.rand(B, N, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.2
    xyz = _cams(res, B=B).project(pts)
    radius = 0.3 + 3 * torch.rand(B, N, generator=gen, dtype=torch.float64)
    m = N // 10
    xyz[:, :m, :2] += 4 * res * (torch.rand(B, m, 2, generator=gen, dtype=torch.float64) - 0.5)  # many off-screen
    xyz[:, m:2 * m, 2] *= -1  # behind the camera
    xyz[:, 2 * m, 0] = float("nan")
    xyz[:, 2 * m + 1] = float("nan")
    xyz[:, 2 * m + 2, 2] = float("inf")
    radius[:, 2 * m + 3] = 0.0
    radius[:, 2 * m + 4] = float("nan")
    xyz[:, 2 * m + 5, :2] = torch.tensor([-0.9, res - 0.2], dtype=torch.float64)  # straddles a corner
    radius[:, 2 * m + 5] = 2.0
    return xyz, radius


@pytest.mark.parametrize("B, N, K, res, chunk_pairs", [(1, 300, 1, 24, 1 << 22), (2, 900, 5, 40, 1 << 22),
                                                      (3, 600, 8, 32, 257), (1, 2000, 3, 20, 50)])
@pytest.mark.parametrize("one_key", [True, False])
def test_torch_splat_equals_numba_kernel_bit_for_bit(B, N, K, res, chunk_pairs, one_key, monkeypatch):
    """The CUDA path's vectorised K-nearest search against the numba kernel: same ids, order and
    depths, also when the pairs are cut into many chunks (lists merged across chunks), with
    off-screen, behind-the-camera, NaN, infinite-depth and zero-radius points, on a non-square
    image, and with the two-sort fallback for keys too large for int64."""
    if not one_key:
        monkeypatch.setattr(kernels, "SPLAT_KEY_LIMIT", 0)
    gen = torch.Generator().manual_seed(10 * B + K)
    xyz, radius = _awkward_cloud(B, N, res, gen)
    for H, W in ((res, res), (res - 5, res + 7)):
        idx, depth = kernels.splat_numba(xyz.numpy(), radius.numpy(), H, W, K)
        vec_idx, vec_depth = kernels.splat_torch(xyz, radius, H, W, K, chunk_pairs=chunk_pairs)
        assert vec_idx.shape == (B, H, W, K) and vec_idx.dtype == torch.int64 and vec_depth.dtype == torch.float64
        np.testing.assert_array_equal(vec_idx.numpy(), idx)
        np.testing.assert_array_equal(vec_depth.numpy(), depth)
        assert (idx[..., K - 1] >= 0).any() and (idx[..., 0] < 0).any()  # full lists and empty pixels occur
        m = N // 10
        assert not np.isin(idx, np.arange(m, 2 * m + 5)).any()  # behind, NaN, inf depth, zero/NaN radius
        assert (idx == 2 * m + 5).any() == (H == res)  # the corner disc shows where the corner is
    scalar = kernels.splat_torch(xyz, torch.tensor(1.5, dtype=torch.float64), res, res, K)  # broadcast radius
    np.testing.assert_array_equal(scalar[0].numpy(), kernels.splat_numba(xyz.numpy(), np.full((B, N), 1.5), res, res, K)[0])
    empty = kernels.splat_torch(xyz[:, :0], radius[:, :0], res, res, K)
    assert empty[0].eq(-1).all() and torch.isinf(empty[1]).all()
    with pytest.raises(ValueError, match="K must be"):
        kernels.splat_torch(xyz, radius, res, res, 0)


def test_torch_splat_equals_torch_reference():
    gen = torch.Generator().manual_seed(3)
    pts = (torch.rand(2, 300, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.15
    xyz = _cams(30, B=2).project(pts)
    radius = 0.5 + 2.5 * torch.rand(2, 300, generator=gen, dtype=torch.float64)
    ref_idx, ref_depth = kernels.splat_reference(xyz, radius, 30, 30, 6)
    idx, depth = kernels.splat_torch(xyz, radius, 30, 30, 6, chunk_pairs=500)
    np.testing.assert_array_equal(idx.numpy(), ref_idx.numpy())
    np.testing.assert_array_equal(depth.numpy(), ref_depth.numpy())


def _random_squash(B, N, gen):
    """(B, N, 3) elliptical footprints: unit directions, s up to 10 (a third of them 0: discs)."""
    u = torch.nn.functional.normalize(torch.randn(B, N, 2, generator=gen, dtype=torch.float64), dim=-1)
    s = 10 * torch.rand(B, N, 1, generator=gen, dtype=torch.float64)
    s[:, ::3] = 0
    return torch.cat([u, s], -1)


@pytest.mark.parametrize("chunk_pairs", [1 << 22, 257])
def test_elliptical_splat_kernels_agree(chunk_pairs):
    """With ``squash`` (surfel footprints) the numba kernel equals the all-pairs reference, the
    vectorised torch search equals the numba kernel bit for bit, and the footprints are narrower
    than the discs (fewer fragments) yet the s = 0 points keep their discs."""
    gen = torch.Generator().manual_seed(7)
    xyz, radius = _awkward_cloud(2, 700, 32, gen)
    squash = _random_squash(2, 700, gen)
    ref_idx, ref_depth = kernels.splat_reference(xyz, radius.nan_to_num(0), 32, 32, 5, squash=squash)
    idx, depth = kernels.splat_numba(xyz.numpy(), radius.numpy(), 32, 32, 5, squash=squash.numpy())
    np.testing.assert_array_equal(ref_idx.numpy(), idx)
    np.testing.assert_array_equal(ref_depth.numpy(), depth)
    vec_idx, vec_depth = kernels.splat_torch(xyz, radius, 32, 32, 5, chunk_pairs=chunk_pairs, squash=squash)
    np.testing.assert_array_equal(vec_idx.numpy(), idx)
    np.testing.assert_array_equal(vec_depth.numpy(), depth)
    discs, _ = kernels.splat_numba(xyz.numpy(), radius.numpy(), 32, 32, 5)
    zero = kernels.splat_numba(xyz.numpy(), radius.numpy(), 32, 32, 5, squash=np.zeros(xyz.shape))[0]
    np.testing.assert_array_equal(zero, discs)
    assert (idx >= 0).sum() < (discs >= 0).sum()


def test_surfels_put_the_outline_at_the_surface():
    """A sphere's surface points drawn as surfels cover the sphere's own outline; as screen-facing
    discs of the same radius they spill about a radius beyond it (why a point avatar of few,
    large points drawn as discs comes out smaller than the head it renders). A face-on surfel is
    the disc, and the splat's gradients reach the normals."""
    R, res, r_world = 0.1, 96, 0.012
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=R)
    pts = torch.tensor(sphere.vertices)[None]
    nrm = torch.tensor(sphere.vertex_normals)[None]
    cams = _cams(res)
    depth = cams.world_to_camera(pts)[..., 2]
    r_px = cams.K[:, 0, 0, None] * r_world / depth
    feats = torch.ones_like(pts[..., :1])
    silhouette = mesh.rasterize(cams, *_sphere(4, R)).mask[0].double()

    def outline_px(image):  # the mask's equivalent radius less the true silhouette's, pixels
        area = lambda m: float(m.sum())  # noqa: E731
        return (area(image.mask[0] > 0.5) ** 0.5 - area(silhouette) ** 0.5) / np.pi ** 0.5

    disc_px = float(r_px.mean())
    discs = points.splat(cams, pts, feats, r_px, K=8)
    surfels = points.splat(cams, pts, feats, r_px, K=8, normals=nrm, min_cos=0.05)
    assert outline_px(discs) > 0.5 * disc_px
    assert abs(outline_px(surfels)) < 0.2 * disc_px
    # face-on (normal along the view ray): the same footprint as a disc
    centre = cams.world_to_camera(torch.zeros(1, 1, 3, dtype=torch.float64))
    one = torch.zeros(1, 1, 3, dtype=torch.float64)
    toward = -torch.nn.functional.normalize(centre, dim=-1) @ cams.R.double()
    a = points.splat(cams, one, torch.ones(1, 1, 1, dtype=torch.float64), 5.0, K=2)
    b = points.splat(cams, one, torch.ones(1, 1, 1, dtype=torch.float64), 5.0, K=2, normals=toward)
    torch.testing.assert_close(b.mask, a.mask)
    n = nrm.clone().requires_grad_()
    points.splat(cams, pts, feats, r_px, K=8, normals=n, min_cos=0.3).mask.sum().backward()
    assert torch.isfinite(n.grad).all() and n.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="min_cos"):
        points.splat(cams, pts, feats, r_px, normals=nrm, min_cos=0.0)
    with pytest.raises(ValueError, match="normals must be"):
        points.splat(cams, pts, feats, r_px, normals=nrm[:, :5])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_splat_torch_backend_equals_numba_backend(dtype):
    """points.splat with backend="torch" (what CUDA tensors get) gives the numba path's
    fragments, features, mask, max_weight and gradients."""
    gen = torch.Generator().manual_seed(4)
    pts = ((torch.rand(2, 500, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.15).to(dtype)
    pts[0, 0] = float("nan")
    pts[1, :20, 2] = 0.8  # behind the camera (distance 0.5)
    feats = torch.rand(2, 500, 3, generator=gen, dtype=dtype)
    radius = (0.8 + 2 * torch.rand(500, generator=gen, dtype=torch.float64)).to(dtype)
    cams = _cams(36, dtype=dtype, B=2)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=dtype)
    outs, grads = [], []
    normals = torch.nn.functional.normalize(torch.randn(2, 500, 3, generator=gen, dtype=torch.float64), dim=-1).to(dtype)
    for backend in ("numba", "torch"):
        p, f, n = pts.clone().requires_grad_(), feats.clone().requires_grad_(), normals.clone().requires_grad_()
        out = points.splat(cams, p, f, radius, K=5, background=bg, backend=backend)
        surfels = points.splat(cams, p, f, radius, K=5, background=bg, backend=backend, normals=n)
        (out.features.square().sum() + out.mask.sum() + surfels.features.square().sum()).backward()
        outs.append(out)
        outs.append(surfels)
        grads.append((p.grad, f.grad, n.grad))
    outs = [(outs[0], outs[2]), (outs[1], outs[3])]
    for a, b in outs:
        torch.testing.assert_close(b.fragments.idx, a.fragments.idx, atol=0, rtol=0)
        torch.testing.assert_close(b.features, a.features, atol=0, rtol=0)
    outs = outs[0]
    a, b = outs
    torch.testing.assert_close(b.fragments.idx, a.fragments.idx, atol=0, rtol=0)
    torch.testing.assert_close(b.fragments.depth, a.fragments.depth, atol=0, rtol=0)
    torch.testing.assert_close(b.features, a.features, atol=0, rtol=0)
    torch.testing.assert_close(b.mask, a.mask, atol=0, rtol=0)
    torch.testing.assert_close(b.max_weight, a.max_weight, atol=0, rtol=0)
    assert torch.equal(b.front, a.front)
    for ga, gb in zip(*grads):
        torch.testing.assert_close(gb, ga, atol=0, rtol=0)
    assert a.mask.max() > 0.9 and b.fragments.depth.dtype == dtype
    with pytest.raises(ValueError, match="backend must be"):
        points.splat(cams, pts, feats, radius, backend="cuda")


def test_point_sampled_sphere_matches_the_analytic_disc():
    R, d, res = 0.1, 0.5, 128
    cams = _cams(res, distance=d)
    pts, _ = trimesh.sample.sample_surface_even(trimesh.creation.icosphere(5, radius=R), 60000, seed=0)
    pts = torch.tensor(pts)[None]
    image = points.splat(cams, pts, torch.ones(1, pts.shape[1], 1, dtype=torch.float64), radius=1.0, K=8)
    covered = (image.mask[0] > 0.5).numpy()
    f = cams.K[0, 0, 0].item()
    radius_px = f * R / math.sqrt(d * d - R * R)  # exact silhouette radius of a sphere on the axis
    ys, xs = np.mgrid[0:res, 0:res]
    c = (res - 1) / 2
    dist = np.hypot(xs - c, ys - c)
    disc = dist < radius_px
    mismatch = covered != disc
    assert np.abs(dist[mismatch] - radius_px).max() <= 1.0  # disagreements only within 1 px of the edge
    assert abs(math.sqrt(covered.sum() / math.pi) - radius_px) < 1.0


def test_point_compositing_gradcheck():
    gen = torch.Generator().manual_seed(1)
    pts = (torch.rand(1, 30, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.04
    feats = torch.rand(1, 30, 2, generator=gen, dtype=torch.float64)
    radius = 2.5 + torch.rand(30, generator=gen, dtype=torch.float64)
    cams = _cams(16)

    def render(p, c, r):
        out = points.splat(cams, p, c, r, K=4)
        return out.features, out.mask

    assert torch.autograd.gradcheck(render, (pts.requires_grad_(), feats.requires_grad_(), radius.requires_grad_()),
                                    eps=1e-7, atol=1e-5)


def test_point_max_weight_and_front_to_back_order():
    cams = _cams(15)  # odd size: the optical axis hits pixel (7, 7) at its centre
    centre = cams.pinhole().centre
    # two points on the optical axis: the nearer one hides most of the farther one
    p = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.05]]], dtype=torch.float64)
    out = points.splat(cams, p, torch.tensor([[[1.0], [0.0]]], dtype=torch.float64), radius=3.0, K=2)
    assert out.max_weight[0, 1] == pytest.approx(1.0)  # the near point (z closer to the camera)
    # the far point shows only where the near disc thins out: weight (1 - a) a <= 1/4
    assert 0.2 < out.max_weight[0, 0] <= 0.25
    assert out.fragments.idx[0, 7, 7, 0].item() == 1 and centre[2] > 0
    assert out.front[0].tolist() == [False, True]  # the far point is nearest on no pixel


def test_point_front_marks_the_first_fragment_of_some_pixel():
    """``front``: the points nearest on at least one pixel (PyTorch3D's first fragment), which
    PointAvatar's prunes keep besides those composited above 1/2 -- in a cloud, some points are
    nearest only where their discs thin out, with a largest weight under 1/2."""
    gen = torch.Generator().manual_seed(7)
    pts = (torch.rand(1, 400, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.12
    out = points.splat(_cams(32), pts, torch.ones(1, 400, 1, dtype=torch.float64), radius=2.0, K=4)
    first = out.fragments.idx[0, ..., 0]
    want = torch.zeros(400, dtype=torch.bool)
    want[first[first >= 0]] = True
    assert torch.equal(out.front[0], want)
    assert (out.front[0] & (out.max_weight[0] <= 0.5)).any() and not out.front[0].all()


def test_points_bad_input():
    cams = _cams(16)
    behind = torch.tensor([[[0.0, 0.0, 0.9]]], dtype=torch.float64)  # behind the camera at z = 0.5
    out = points.splat(cams, behind, torch.ones(1, 1, 3, dtype=torch.float64), 2.0)
    assert out.mask.sum() == 0
    nan = torch.full((1, 2, 3), float("nan"), dtype=torch.float64)
    assert points.splat(cams, nan, torch.ones(1, 2, 3, dtype=torch.float64), 2.0).mask.sum() == 0
    mixed = (torch.randn(1, 20, 3, dtype=torch.float64) * 0.03)
    mixed[0, 0] = float("nan")
    mixed.requires_grad_()
    points.splat(cams, mixed, torch.ones(1, 20, 3, dtype=torch.float64), 2.0).features.sum().backward()
    assert torch.isfinite(mixed.grad).all()
    with pytest.raises(ValueError, match="radius must be"):
        points.splat(cams, behind, torch.ones(1, 1, 3), torch.ones(3))
    with pytest.raises(ValueError, match="features must be"):
        points.splat(cams, behind, torch.ones(1, 2, 3), 2.0)


# ---- shading ------------------------------------------------------------------------------
def test_constant_sh_gives_uniform_irradiance_and_matches_lambert_first_band():
    n = torch.nn.functional.normalize(torch.randn(100, 3, dtype=torch.float64), dim=-1)
    torch.testing.assert_close(shading.sh_shading(n, shading.constant_sh(0.7).double()),
                               torch.full((100, 3), 0.7, dtype=torch.float64))
    lit = shading.lambert(n, torch.ones(100, 3, dtype=torch.float64), (0.0, 0.0, 1.0), ambient=0.0)
    torch.testing.assert_close(lit[:, 0], n[:, 2].clamp(min=0))


def test_scale_intrinsics_keeps_pixel_centres():
    from headforge.render.camera import scale_intrinsics

    K = torch.tensor([[900.0, 0, 255.5], [0, 900.0, 255.5], [0, 0, 1]])
    small = scale_intrinsics(K, 0.5)
    point = torch.tensor([0.03, -0.02, 0.8])
    big_px = (K @ point)[:2] / point[2]
    small_px = (small @ point)[:2] / point[2]
    assert torch.allclose(small_px, (big_px + 0.5) * 0.5 - 0.5, atol=1e-4)
    assert K[0, 0] == 900.0  # the input is not modified


def test_soft_matte_widens_only_the_edge_and_keeps_the_surface_colour():
    from headforge.render.matte import fit_sigma, gaussian_blur, soft_matte

    cov = torch.zeros(1, 64, 64)
    cov[:, 16:48, 20:44] = 1.0
    colour = torch.tensor([0.2, 0.5, 0.7])
    rgb = cov[..., None] * colour + (1 - cov[..., None])  # on white
    same_rgb, same_cov = soft_matte(rgb, cov, 0.0)
    assert torch.equal(same_rgb, rgb) and torch.equal(same_cov, cov)
    out, alpha = soft_matte(rgb, cov, 1.5)
    assert torch.allclose(alpha, gaussian_blur(cov[..., None], 1.5)[..., 0])
    assert abs(float(alpha.sum() - cov.sum())) < 1e-3 * float(cov.sum())  # the blur keeps the matte's mass
    deep = torch.zeros_like(cov, dtype=torch.bool)
    deep[:, 24:40, 28:36] = True
    assert torch.allclose(out[deep], rgb[deep])  # interior untouched
    # outside the shape the soft edge fades the surface's colour into the background, nothing else
    assert torch.allclose(out, alpha[..., None] * colour + (1 - alpha[..., None]), atol=1e-5)
    assert alpha[0, 32, 18] > 0.05 and alpha[0, 32, 20] < 1  # wider than the hard edge, on both sides
    # the sigma of a matted target is recovered from the hard render
    target, _ = soft_matte(rgb, cov, 1.25)
    sigma, scores = fit_sigma(rgb, cov, target, torch.ones_like(cov))
    assert sigma == 1.25 and min(s for _, s in scores) < 1e-10


def test_close_holes_fills_gaps_between_splats_with_their_neighbours_mean_and_keeps_the_outline():
    from headforge.render.points import close_holes

    covered = torch.zeros(1, 12, 12, dtype=torch.bool)
    covered[0, 2:10, 2:10] = True
    covered[0, 5, 5] = False  # a one-pixel hole
    covered[0, 3, 6:8] = False  # a two-pixel hole
    values = torch.randn(1, 12, 12, 3)
    filled, closed = close_holes(values, covered)
    want = torch.zeros(1, 12, 12, dtype=torch.bool)
    want[0, 2:10, 2:10] = True
    assert torch.equal(closed, want)  # the holes closed, the square's outline kept
    assert torch.equal(filled[covered], values[covered])
    assert (filled[~closed] == 0).all()
    ring = [(4, 4), (4, 5), (4, 6), (5, 4), (5, 6), (6, 4), (6, 5), (6, 6)]
    mean = torch.stack([values[0, y, x] for y, x in ring]).mean(0)
    assert torch.allclose(filled[0, 5, 5], mean, atol=1e-6)
    # a pixel of the wide hole averages its covered neighbours only (not its uncovered twin)
    around = [(y, x) for y in (2, 3, 4) for x in (5, 6, 7) if covered[0, y, x]]
    assert torch.allclose(filled[0, 3, 6], torch.stack([values[0, y, x] for y, x in around]).mean(0), atol=1e-6)
