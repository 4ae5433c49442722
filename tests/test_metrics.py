"""Metrics against independent references: scikit-image, pytorch-msssim, scipy, brute force,
closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.distance import directed_hausdorff

from headforge.errors import HeadforgeError
from headforge.metrics import distribution, geometry, image


def _pair(B=2, H=180, W=170, seed=0):
    gen = torch.Generator().manual_seed(seed)
    gt = torch.rand(B, H, W, 3, generator=gen, dtype=torch.float64)
    gt = torch.nn.functional.avg_pool2d(gt.permute(0, 3, 1, 2), 5, 1, 2).permute(0, 2, 3, 1)  # some structure
    pred = (gt + 0.05 * torch.randn(gt.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    return pred, gt


def test_l1_psnr_hand_cases():
    gt = torch.zeros(1, 4, 4, 3, dtype=torch.float64)
    pred = gt + 0.1
    assert image.l1(pred, gt).item() == pytest.approx(0.1)
    assert image.psnr(pred, gt).item() == pytest.approx(20.0)
    mask = torch.zeros(1, 4, 4)
    mask[0, :2] = 1
    pred[0, 2:] = 1.0  # error outside the mask is ignored
    assert image.psnr(pred, gt, mask).item() == pytest.approx(20.0)


def test_ssim_matches_scikit_image():
    from skimage.metrics import structural_similarity

    pred, gt = _pair()
    ours = image.ssim(pred, gt)
    for b in range(2):
        ref = structural_similarity(pred[b].numpy(), gt[b].numpy(), gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, data_range=1.0, channel_axis=-1)
        assert ours[b].item() == pytest.approx(ref, abs=1e-6)
    assert image.ssim(gt, gt).min().item() == pytest.approx(1.0)


def test_ms_ssim_matches_pytorch_msssim():
    from pytorch_msssim import ms_ssim

    pred, gt = _pair(H=200, W=192)
    ref = ms_ssim(pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2), data_range=1.0, size_average=False)
    torch.testing.assert_close(image.ms_ssim(pred, gt), ref, atol=1e-5, rtol=1e-5)


def test_masked_ssim_ignores_outside_pixels():
    pred, gt = _pair(B=1)
    mask = torch.zeros(gt.shape[:3])
    mask[:, 40:140, 40:130] = 1
    broken = pred.clone()
    broken[:, :20] = 0  # far outside the mask (and its 5 px window margin)
    torch.testing.assert_close(image.ssim(broken, gt, mask), image.ssim(pred, gt, mask))
    assert image.ssim(broken, gt).item() < image.ssim(pred, gt).item()


def test_image_metric_bad_input():
    pred, gt = _pair(B=1, H=32, W=32)
    with pytest.raises(HeadforgeError, match="one shape"):
        image.l1(pred, gt[:, :16])
    with pytest.raises(HeadforgeError, match="mask is empty"):
        image.psnr(pred, gt, torch.zeros(1, 32, 32))
    with pytest.raises(HeadforgeError, match="MS-SSIM needs images larger"):
        image.ms_ssim(pred, gt)


def test_lpips_is_none_without_the_package_or_its_weights(monkeypatch):
    """This environment has neither the ``lpips`` package nor its AlexNet weights: None. A
    package whose model cannot load its weights (no network) gives None too, never a crash."""
    import sys
    import types

    pred, gt = _pair(B=1, H=64, W=64)
    monkeypatch.setitem(sys.modules, "lpips", None)  # `import lpips` raises ImportError
    assert image.lpips(pred, gt) is None

    def no_weights(**kwargs):
        raise OSError("cannot download alexnet weights")

    monkeypatch.setitem(sys.modules, "lpips", types.SimpleNamespace(LPIPS=no_weights))
    assert image.lpips(pred, gt) is None


def test_lpips_loading_path_calls_the_model_on_nchw_images_in_minus_one_one(monkeypatch):
    """With the package and weights present, the model is built as AlexNet LPIPS and gets
    (B, C, H, W) images scaled to [-1, 1]; one value per image comes back. A stand-in model
    (the real weights cannot be had here) records what it is given."""
    import sys
    import types

    seen = {}

    class FakeLPIPS(torch.nn.Module):
        def __init__(self, **kwargs):
            super().__init__()
            seen["kwargs"] = kwargs

        def forward(self, a, b):
            seen["shape"], seen["range"] = a.shape, (min(a.min(), b.min()).item(), max(a.max(), b.max()).item())
            return (a - b).abs().mean((1, 2, 3), keepdim=True)  # (B, 1, 1, 1) as lpips returns

    monkeypatch.setitem(sys.modules, "lpips", types.SimpleNamespace(LPIPS=FakeLPIPS))
    gt = torch.zeros(2, 16, 24, 3)
    pred = torch.ones(2, 16, 24, 3)
    value = image.lpips(pred, gt)
    assert seen["kwargs"]["net"] == "alex" and seen["kwargs"]["pretrained"] is True
    assert seen["shape"] == (2, 3, 16, 24) and seen["range"] == (-1.0, 1.0)
    assert value.shape == (2,) and torch.allclose(value, torch.full((2,), 2.0))


def test_fid_and_kid_closed_forms():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(4000, 4, generator=gen, dtype=torch.float64)
    b = torch.randn(4000, 4, generator=gen, dtype=torch.float64) * 2 + 1
    # Gaussians N(0, I) and N(1, 4I): FID = |mu|^2 + tr(I + 4I - 2*2I) = 4 + 4
    assert image.fid_from_features(a, b) == pytest.approx(8.0, rel=0.05)
    assert abs(image.kid_from_features(a, a[torch.randperm(4000, generator=gen)])) < 1e-2
    assert image.kid_from_features(a, b) > 0.5


def test_normal_angle_error_hand_case():
    n = torch.zeros(1, 2, 2, 3)
    n[..., 2] = 1
    tilted = n.clone()
    tilted[0, 0, 0] = torch.tensor([1.0, 0.0, 1.0])  # 45 degrees
    mask = torch.ones(1, 2, 2)
    assert geometry.normal_angle_error(tilted, n, mask).item() == pytest.approx(45 / 4)
    mask[0, 0, 0] = 0
    assert geometry.normal_angle_error(tilted, n, mask).item() == pytest.approx(0.0, abs=1e-5)


def test_hausdorff_against_scipy_and_exact_sphere():
    sphere = trimesh.creation.icosphere(4, radius=1.0)
    bigger = trimesh.creation.icosphere(4, radius=1.01)
    h = geometry.one_sided_hausdorff(bigger.vertices, bigger.faces, sphere.vertices, sphere.faces, samples=5000)
    assert 0.0095 < h["mean"] < 0.0101 and h["max"] < 0.012
    # against scipy's directed Hausdorff between dense point sets
    pts, _ = trimesh.sample.sample_surface(bigger, 3000, seed=1)
    ours = geometry.points_to_mesh(pts, sphere.vertices, sphere.faces).max()
    dense, _ = trimesh.sample.sample_surface(sphere, 400_000, seed=2)
    ref = directed_hausdorff(pts, dense)[0]
    assert ours <= ref + 1e-9 and ref - ours < 0.006  # the surface is at least as close as its samples
    with pytest.raises(HeadforgeError, match="no faces"):
        geometry.one_sided_hausdorff(sphere.vertices, sphere.faces, sphere.vertices, np.zeros((0, 3), int))


def test_chamfer_and_normal_consistency_brute_force():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(60, 3)), rng.normal(size=(50, 3))
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    assert geometry.chamfer(a, b) == pytest.approx((d.min(1) ** 2).mean() + (d.min(0) ** 2).mean())
    na, nb = rng.normal(size=(60, 3)), rng.normal(size=(50, 3))
    ua, ub = na / np.linalg.norm(na, axis=1, keepdims=True), nb / np.linalg.norm(nb, axis=1, keepdims=True)
    ref = 0.5 * (np.abs((ua * ub[d.argmin(1)]).sum(1)).mean() + np.abs((ub * ua[d.argmin(0)]).sum(1)).mean())
    assert geometry.normal_consistency(a, na, b, nb) == pytest.approx(ref)


def test_distribution_metrics_brute_force():
    rng = np.random.default_rng(1)
    gen = [rng.normal(0, 0.1, (40, 3)) for _ in range(5)]
    ref = [rng.normal(0, 0.1, (40, 3)) + 0.05 * i for i in range(4)]

    def cd(x, y):
        d = np.linalg.norm(x[:, None] - y[None], axis=-1)
        return (d.min(1) ** 2).mean() + (d.min(0) ** 2).mean()

    M = np.array([[cd(g, r) for r in ref] for g in gen])
    out = distribution.mmd_cov_1nna(gen, ref)
    assert out["mmd_cd"] == pytest.approx(M.min(0).mean())
    assert out["cov_cd"] == pytest.approx(len(set(M.argmin(1))) / len(ref))
    both = gen + ref
    labels = [0] * len(gen) + [1] * len(ref)
    correct = 0
    for i, x in enumerate(both):
        dist = [cd(x, y) if j != i else np.inf for j, y in enumerate(both)]
        correct += labels[int(np.argmin(dist))] == labels[i]
    assert out["1nna_cd"] == pytest.approx(correct / len(both))
    # the symmetric matrix computes each pair once and equals the full one
    assert np.allclose(distribution.pairwise_chamfer(gen), distribution.pairwise_chamfer(gen, gen))
    # COV over a subset of the references (HeadCraft's neutral scans) from the shared matrices
    cols = np.array([True, False, True, True])
    sub = distribution.mmd_cov_1nna_from(M, distribution.pairwise_chamfer(gen), distribution.pairwise_chamfer(ref), cols)
    assert sub["cov_cd"] == pytest.approx(len(set(M[:, cols].argmin(1))) / cols.sum())
    assert sub["mmd_cd"] == pytest.approx(out["mmd_cd"]) and sub["1nna_cd"] == pytest.approx(out["1nna_cd"])
    with pytest.raises(HeadforgeError, match="mismatched"):
        distribution.mmd_cov_1nna_from(M.T, distribution.pairwise_chamfer(gen), distribution.pairwise_chamfer(ref))


def test_jsd_hand_cases():
    a = [np.array([[0.1, 0.1, 0.1]])]
    b = [np.array([[-0.3, -0.3, -0.3]])]
    assert distribution.jsd(a, a) == pytest.approx(0.0)
    assert distribution.jsd(a, b) == pytest.approx(math.log(2))  # disjoint supports
    with pytest.raises(HeadforgeError, match="no points fall inside"):
        distribution.jsd([np.full((3, 3), 5.0)], a)


def test_eval_command(tmp_path):
    import json
    import subprocess
    import sys

    from PIL import Image

    rng = np.random.default_rng(0)
    for d in ("pred", "gt", "masks"):
        (tmp_path / d).mkdir()
    for i in range(3):
        gt = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
        pred = np.clip(gt.astype(int) + rng.integers(-10, 10, gt.shape), 0, 255).astype(np.uint8)
        Image.fromarray(gt).save(tmp_path / "gt" / f"{i}.png")
        Image.fromarray(pred).save(tmp_path / "pred" / f"{i}.png")
        mask = np.zeros((64, 64), np.uint8)
        mask[16:48, 16:48] = 255
        Image.fromarray(mask).save(tmp_path / "masks" / f"{i}.png")
    cmd = [sys.executable, "-m", "headforge.cli", "eval", str(tmp_path / "pred"), str(tmp_path / "gt"),
           "--masks", str(tmp_path / "masks"), "-o", str(tmp_path / "out"), "--json"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["images"] == 3 and 25 < summary["psnr"] < 40 and 0 <= summary["cpbd"] <= 1
    # LPIPS: "n/a" when its package or weights are absent (always, here), a number otherwise
    if image.lpips(torch.zeros(1, 64, 64, 3), torch.rand(1, 64, 64, 3)) is None:
        assert summary["lpips"] == "n/a" and "| lpips | n/a |" in (tmp_path / "out" / "metrics.md").read_text()
    else:
        assert 0 <= summary["lpips"] < 1
    assert {"ssim_masked", "psnr_masked"} <= set(summary)
    assert (tmp_path / "out" / "grid.png").is_file() and "3 images" in (tmp_path / "out" / "metrics.md").read_text()
    (tmp_path / "pred" / "2.png").unlink()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 1 and "have no prediction" in proc.stderr and "2.png" in proc.stderr


def test_cpbd_matches_the_reference_package():
    """The cpbd package (1.0.7) imports scipy.ndimage.imread, removed from SciPy; its compute()
    does not use it, so a stand-in attribute lets it serve as the reference."""
    import scipy.ndimage
    from scipy.ndimage import gaussian_filter
    from skimage import data

    if not hasattr(scipy.ndimage, "imread"):
        scipy.ndimage.imread = None
    reference = pytest.importorskip("cpbd.compute").compute
    values = []
    for name in ("camera", "coffee"):
        img = getattr(data, name)().astype(float) / 255
        img = img @ np.array([0.299, 0.587, 0.114]) if img.ndim == 3 else img
        for sigma in (0, 1.5):
            blurred = gaussian_filter(img, sigma) if sigma else img
            ours = image.cpbd(blurred)
            assert ours == pytest.approx(reference(blurred * 255), abs=2e-3)
            values.append(ours)
    assert values[0] > values[1] and values[2] > values[3]  # blur lowers CPBD


def test_landmark_scores_split_akd_by_face_region():
    """The regions partition MediaPipe's 478 landmarks; a shift of the lips alone shows in the lips'
    AKD, in the mouth opening and in the all-landmark AKD by the lips' share, nowhere else."""
    from headforge.metrics.protocol import landmark_regions, landmark_scores

    regions = landmark_regions()
    every = np.concatenate(list(regions.values()))
    assert len(every) == 478 and set(every.tolist()) == set(range(478))
    rng = np.random.default_rng(0)
    truth = rng.uniform(50, 200, (2, 478, 2))
    upper_lip, lower_lip = np.array([13, 82, 312]), np.array([14, 87, 317])  # the inner-lip pairs
    truth[:, lower_lip] = truth[:, upper_lip] + np.array([0.0, 10.0])  # each lower point 10 px below its upper one
    pred = truth.copy()
    assert set(lower_lip) <= set(regions["lips"].tolist())
    pred[:, regions["lips"], 1] += 3.0
    pred[:, lower_lip, 1] += 2.0  # the mouth opens by 2 px more
    s = landmark_scores(pred, truth, by_region=True)
    lips = np.full(len(regions["lips"]), 3.0)
    lips[np.isin(regions["lips"], lower_lip)] = 5.0
    np.testing.assert_allclose(s["akd_lips_px"], lips.mean())
    np.testing.assert_allclose(s["akd_px"], lips.sum() / 478)
    np.testing.assert_allclose(s["mouth_opening_error_px"], 2.0)
    np.testing.assert_allclose(s["mouth_opening_avatar_px"] - s["mouth_opening_frame_px"], 2.0)  # the sign
    np.testing.assert_allclose(s["mouth_opening_frame_px"], 10.0)
    for name in regions:
        if name != "lips":
            np.testing.assert_allclose(s[f"akd_{name}_px"], 0.0)
    np.testing.assert_allclose(s["eye_opening_error_px"], 0.0)
    assert "akd_lips_px" not in landmark_scores(pred, truth)
    # a face drawn 4 px to the right of the frame's: all of AKD is the shift
    shifted = landmark_scores(truth + np.array([4.0, 0.0]), truth, by_region=True)
    np.testing.assert_allclose(shifted["akd_px"], 4.0)
    np.testing.assert_allclose(shifted["landmark_shift_px"], 4.0)
    np.testing.assert_allclose(shifted["akd_unshifted_px"], 0.0, atol=1e-9)
    np.testing.assert_allclose(s["landmark_shift_px"], lips.sum() / 478)  # the lips' mean displacement, spread over the face


def test_similarity_alignment_recovers_a_scaled_head():
    """A head s times too large (what a monocular clip cannot tell from one s times farther):
    the rigid face alignment leaves millimetres, the similarity alignment finds 1/s and puts the
    face back on the GT."""
    from headforge.metrics.benchmark import _face_samples, _icp_to_face, _moved, similarity_to_face, transform_scale

    gt = trimesh.creation.icosphere(subdivisions=4)
    gt.apply_scale([0.075, 0.1, 0.09])  # an ellipsoid head (m): no symmetry lets a shift stand in for a scale
    gt.apply_translation([0.0, 0.0, 0.9])
    gv, gf = np.asarray(gt.vertices), np.asarray(gt.faces)
    face_vertices = (gv[:, 2] < 0.9 - 0.03) & (gv[:, 1] > -0.06)  # the camera-facing front, cut unevenly
    s = 1.12
    angle = np.deg2rad(3.0)
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    pred = s * (gv - gv.mean(0)) @ rot.T + gv.mean(0) + [0.004, -0.002, 0.06]  # larger, turned, farther
    pred_face_faces = gf[face_vertices[gf].all(1)]
    source = _face_samples(pred, pred_face_faces)
    rigid = _icp_to_face(source, gv, gf, face_vertices)
    similar = similarity_to_face(source, gv, gf, np.ones(len(gv), bool), rigid)
    assert transform_scale(similar) == pytest.approx(1 / s, rel=0.01)
    d_rigid = geometry.points_to_mesh(_moved(source, rigid), gv, gf)
    d_similar = geometry.points_to_mesh(_moved(source, similar), gv, gf)
    assert d_rigid.mean() > 2e-3 and d_similar.mean() < 3e-4
