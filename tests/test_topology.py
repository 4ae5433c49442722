"""Subdivision (NHA, HeadCraft), region cut, hole closing, smoothing, normals and TBN frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from headforge.errors import HeadforgeError
from headforge.head import topology
from headforge.head.model import HeadModel


def test_subdivision_counts_and_midpoints(tiny_data):
    sub = topology.subdivide(tiny_data.faces, len(tiny_data.v_template))
    V, F = len(tiny_data.v_template), len(tiny_data.faces)
    E = len(trimesh.Trimesh(tiny_data.v_template, tiny_data.faces, process=False).edges_unique)
    assert len(sub.edges) == E and sub.faces.shape == (4 * F, 3)
    pos = sub.carry(tiny_data.v_template)
    np.testing.assert_allclose(pos[V:], 0.5 * (pos[sub.edges[:, 0]] + pos[sub.edges[:, 1]]))
    mesh = trimesh.Trimesh(pos, sub.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent  # orientation kept


def test_subdivided_head_carries_every_attribute(tiny_data):
    """Blendshapes are linear: subdividing commutes with shape/expression. Skinning is not
    linear in (weights x positions), so under a pose it commutes only where both parents of
    a midpoint share their weights."""
    dense = topology.subdivide_head(tiny_data)
    sub = topology.subdivide(tiny_data.faces, len(tiny_data.v_template))
    coarse_model = HeadModel(tiny_data, use_pose_correctives=False)
    fine_model = HeadModel(dense, use_pose_correctives=False)
    linear = dict(shape=torch.randn(2, 4), expression=torch.randn(2, 3))
    coarse, fine = coarse_model(**linear), fine_model(**linear)
    expected = np.stack([sub.carry(v) for v in coarse.vertices.numpy()])
    np.testing.assert_allclose(fine.vertices.numpy(), expected, atol=1e-6)
    torch.testing.assert_close(fine.landmarks, coarse.landmarks, atol=1e-6, rtol=0)
    posed = dict(linear, neck_pose=0.3 * torch.randn(2, 3), jaw_pose=0.2 * torch.randn(2, 3))
    coarse, fine = coarse_model(**posed), fine_model(**posed)
    expected = np.stack([sub.carry(v) for v in coarse.vertices.numpy()])
    same = np.all(tiny_data.weights[sub.edges[:, 0]] == tiny_data.weights[sub.edges[:, 1]], axis=1)
    rows = np.concatenate([np.arange(len(tiny_data.v_template)), len(tiny_data.v_template) + np.nonzero(same)[0]])
    np.testing.assert_allclose(fine.vertices.numpy()[:, rows], expected[:, rows], atol=1e-6)
    assert set(dense.regions) == set(tiny_data.regions)
    assert all(len(dense.regions[k]) >= len(tiny_data.regions[k]) for k in dense.regions)


def test_child_point_round_trip():
    faces = np.array([[0, 1, 2]])
    verts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    sub = topology.subdivide(faces, 3)
    fine = sub.carry(verts)
    rng = np.random.default_rng(0)
    bary = rng.dirichlet([1, 1, 1], size=200)
    child, child_bary = sub.child_point(np.zeros(200, int), bary)
    assert (child_bary >= -1e-12).all()
    np.testing.assert_allclose((fine[sub.faces[child]] * child_bary[..., None]).sum(1), bary @ verts, atol=1e-12)


def test_consistent_subdivision_matches_direct_subdivision(tiny_data):
    cs = topology.ConsistentSubdivision(tiny_data.faces, len(tiny_data.v_template), levels=2).bind(tiny_data.faces)
    V = len(tiny_data.v_template)
    once = topology.subdivide(tiny_data.faces, V)
    twice = topology.subdivide(once.faces, V + len(once.edges))
    other_identity = tiny_data.v_template + 0.01 * np.random.default_rng(1).normal(size=(V, 3))
    direct = twice.carry(once.carry(other_identity))
    np.testing.assert_allclose(cs.apply(torch.tensor(other_identity)).numpy(), direct, atol=1e-12)
    np.testing.assert_array_equal(cs.faces, twice.faces)
    batch = cs.apply(torch.tensor(np.stack([other_identity, tiny_data.v_template])))
    assert batch.shape == (2, len(direct), 3)


def test_remove_lower_neck(tiny_data):
    cut = topology.remove_region(tiny_data, "lower_neck")
    assert "lower_neck" not in cut.regions
    assert len(cut.v_template) == len(tiny_data.v_template) - len(tiny_data.regions["lower_neck"])
    HeadModel(cut)(neck_pose=torch.full((1, 3), 0.2))
    with pytest.raises(HeadforgeError, match="no region 'nope'"):
        topology.remove_region(tiny_data, "nope")


def test_close_hole_makes_the_mesh_watertight(tiny_data):
    cut = topology.remove_region(tiny_data, "lower_neck")
    assert len(topology.boundary_loops(cut.faces)) == 1
    closed = topology.close_hole_near(cut, np.array([0.0, -0.1, 0.0]))
    mesh = trimesh.Trimesh(closed.v_template, closed.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert topology.boundary_loops(closed.faces) == []


def test_laplacian_smoothing_respects_per_vertex_strength(tiny_data):
    verts = torch.tensor(tiny_data.v_template) + 0.005 * torch.randn(len(tiny_data.v_template), 3, dtype=torch.float64)
    faces = torch.tensor(tiny_data.faces)
    strength = torch.zeros(len(verts), dtype=torch.float64)
    strength[: len(verts) // 2] = 0.5
    smooth = topology.laplacian_smooth(verts, faces, strength, iterations=5)
    torch.testing.assert_close(smooth[len(verts) // 2:], verts[len(verts) // 2:])
    rough = lambda x: (x - topology.laplacian_smooth(x, faces, 1.0)).norm(dim=-1)[: len(verts) // 2].mean()  # noqa: E731
    assert rough(smooth) < 0.5 * rough(verts)


def test_normals_and_tbn_frames(tiny_data):
    v = torch.tensor(tiny_data.v_template)
    faces = torch.tensor(tiny_data.faces)
    n = topology.vertex_normals(v, faces)
    assert ((n * torch.nn.functional.normalize(v, dim=-1)).sum(-1) > 0.99).all()  # sphere: outward
    tbn = topology.tbn_frames(v[None], faces, torch.tensor(tiny_data.uvs), torch.tensor(tiny_data.uv_faces))
    eye = torch.eye(3, dtype=tbn.dtype).expand_as(tbn)
    ok = torch.isfinite(tbn).all(-1).all(-1)
    assert ok.float().mean() > 0.9
    torch.testing.assert_close((tbn.transpose(-1, -2) @ tbn)[ok], eye[ok], atol=1e-6, rtol=0)
    assert (torch.linalg.det(tbn[ok]) > 0).all()


def test_open_head_template_edits(open_head_data):
    """NHA's template on open-head: lower neck cut, then 4-way subdivided. The cut keeps the
    joints (open-head regresses its neck joint partly from the lower neck): the kept vertices
    pose exactly as in the full model."""
    cut = topology.remove_region(open_head_data, "lower_neck")
    assert np.abs(open_head_data.j_regressor[:, open_head_data.regions["lower_neck"]]).sum() > 0  # the case that matters
    torch.manual_seed(0)
    S, E = open_head_data.shapedirs.shape[2], open_head_data.exprdirs.shape[2]
    params = dict(shape=torch.randn(2, S), expression=torch.randn(2, E), root_pose=0.2 * torch.randn(2, 3),
                  neck_pose=0.3 * torch.randn(2, 3), jaw_pose=0.1 * torch.randn(2, 3))
    full, part = HeadModel(open_head_data)(**params), HeadModel(cut)(**params)
    kept = np.setdiff1d(np.arange(len(open_head_data.v_template)), open_head_data.regions["lower_neck"])
    kept = kept[np.isin(kept, np.unique(open_head_data.faces[~np.isin(open_head_data.faces, open_head_data.regions["lower_neck"]).any(1)]))]
    torch.testing.assert_close(part.vertices, full.vertices[:, kept], atol=1e-6, rtol=0)
    dense = topology.subdivide_head(cut)
    assert len(dense.faces) == 4 * len(cut.faces)
    model = HeadModel(dense)
    out = model(jaw_pose=torch.tensor([[0.2, 0.0, 0.0]]))
    assert out.landmarks.shape == (1, 478, 3) and torch.isfinite(out.vertices).all()
