"""Point-set predictions in the synthetic geometry benchmark (``headforge eval PRED SUBJECT`` for
point avatars): the format, its checks, the engine's export and the protocol's figures on point
sets sampled from the ground truth itself."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.numpy import save_file

from headforge.errors import HeadforgeError


def _write_points(folder, frames, points, normals, radius, surfel_min_cos: float = 0.0,
                  hole_filling: bool = False) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    extra = {"surfel_min_cos": np.array([surfel_min_cos], np.float32)} if surfel_min_cos else {}
    if hole_filling:
        extra["hole_filling"] = np.array([1], np.uint8)
    save_file({"frames": frames.astype(np.int64), "points": np.ascontiguousarray(points, np.float32),
               "normals": np.ascontiguousarray(normals, np.float32), "radius": np.ascontiguousarray(radius, np.float32)}
              | extra, str(folder / "geometry.safetensors"))


@pytest.fixture(scope="module")
def point_sets(synth_bench, tmp_path_factory):
    """The synth subject, how to score its first val GT frame alone (``every``), and prediction
    folders: ``clean`` (40k points on the GT head, radius 1.5 x spacing), ``flipped`` (the same,
    every normal negated), ``noisy`` (normals + N(0, 0.5) noise, renormalised) and ``mesh`` (the
    GT head faces themselves, as an exported mesh)."""
    from headforge.metrics.benchmark import load_subject_gt, sample_gt_head, split_rows

    out, _, _ = synth_bench
    subject = out / "subject_00"
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, "val", 1)
    points, normals, spacing, faces = sample_gt_head(gt, info, 40_000)
    radius = np.full(points.shape[:2], 1.5 * spacing, np.float32)
    root = tmp_path_factory.mktemp("point_sets")
    frames = gt["frames"]
    _write_points(root / "clean", frames, points, normals, radius)
    _write_points(root / "flipped", frames, points, -normals, radius)
    noisy = normals + np.random.default_rng(1).normal(0, 0.5, normals.shape).astype(np.float32)
    _write_points(root / "noisy", frames, points, noisy / np.linalg.norm(noisy, axis=-1, keepdims=True), radius)
    (root / "mesh").mkdir()
    save_file({"frames": frames.astype(np.int64), "vertices": gt["vertices"].astype(np.float32),
               "faces": faces.astype(np.int64), "face_vertices": gt["labels"] == info["labels"]["face"],
               "head_vertices": np.isin(gt["labels"], info["head_labels"])}, str(root / "mesh" / "geometry.safetensors"))
    outer = np.zeros(len(gt["vertices"][0]), bool)
    outer[faces.ravel()] = True  # the vertices of the sampled (outer head) faces
    return {"subject": subject, "every": len(rows), "spacing": spacing, "outer": outer, **{k: root / k for k in
                                                                           ("clean", "flipped", "noisy", "mesh")}}


def test_a_point_set_sampled_on_the_ground_truth_scores_near_perfect(point_sets):
    """Points on the GT head with its normals: on the surface (distances ~0), consistent normals,
    a small splatted normal error and the coverage of the GT head mesh itself; then the same
    points with flipped or noisy normals score worse where each should."""
    from headforge.metrics.benchmark import evaluate_geometry, paired_normal_error

    subject, every = point_sets["subject"], point_sets["every"]
    result = evaluate_geometry(point_sets["clean"], subject, every=every, samples=2000)
    assert result["kind"] == "points" and result["frames"] == 1
    m = result["mean"]
    # both ways: the seen GT's flat strand faces against the samples' smooth normals cap it below 1
    assert m["normal_consistency"] > 0.96
    assert m["hausdorff_full_camera_mm"] < 0.01 and m["hausdorff_face_camera_mm"] < 0.01
    assert m["hausdorff_full_mm"] < 0.3 and m["hausdorff_face_mm"] < 0.3  # the ICP settles within 0.3 mm
    assert m["hausdorff_full_outer_mm"] < 0.3  # sampled on the outer surface only
    assert m["hausdorff_full_scaled_mm"] < 0.3 and m["alignment_scale"] == pytest.approx(1, abs=0.01)
    assert m["normal_error_face_deg"] < 8 and m["normal_error_head_deg"] < 10
    assert m["face_points"] > 0.2 * m["head_points"] and m["head_points"] >= 1990  # ~every point is on the head
    R = int(json.loads((subject / "gt" / "subject.json").read_text())["resolution"])
    assert result["views"].shape == (2 * R, 4 * R, 3)
    # the GT head mesh as the reference: the point set covers what it covers
    pair = paired_normal_error(point_sets["clean"], point_sets["mesh"], subject, every=every)["mean"]
    assert abs(pair["coverage"] - m["head_coverage"]) < 1e-6
    assert abs(pair["coverage"] - pair["reference_coverage"]) < 0.02 and pair["reference_coverage"] > 0.95
    assert pair["common_coverage"] <= min(pair["coverage"], pair["reference_coverage"])
    assert pair["reference_normal_error_head_deg"] < 1 < pair["normal_error_head_deg"]
    # flipped normals: the same |cos| consistency and distances, but the normal maps point away
    flipped = evaluate_geometry(point_sets["flipped"], subject, every=every, samples=2000)["mean"]
    assert abs(flipped["normal_consistency"] - m["normal_consistency"]) < 1e-6
    assert flipped["hausdorff_full_camera_mm"] == pytest.approx(m["hausdorff_full_camera_mm"])
    assert flipped["normal_error_head_deg"] > 150
    # noisy normals: less consistent and a larger normal error
    noisy = evaluate_geometry(point_sets["noisy"], subject, every=every, samples=2000)["mean"]
    assert noisy["normal_consistency"] < m["normal_consistency"] - 0.05
    assert noisy["normal_error_head_deg"] > m["normal_error_head_deg"] + 5


def test_normal_consistency_charges_the_seen_head_a_prediction_leaves_out(point_sets, tmp_path):
    """Normal consistency runs both ways: half the clean points (one side of the head dropped)
    keep their own normals' agreement with the GT, but the seen GT surface on the dropped side
    finds its nearest points on the other half, so the figure falls."""
    from safetensors.numpy import load_file

    from headforge.metrics.benchmark import evaluate_geometry

    subject, every = point_sets["subject"], point_sets["every"]
    arrays = load_file(str(point_sets["clean"] / "geometry.safetensors"))
    pts = arrays["points"]
    keep = pts[0, :, 0] > np.median(pts[0, :, 0])  # one side of the head (camera x), the same points every frame
    _write_points(tmp_path / "half", arrays["frames"], pts[:, keep], arrays["normals"][:, keep], arrays["radius"][:, keep])
    full = evaluate_geometry(point_sets["clean"], subject, every=every, samples=2000)["mean"]
    half = evaluate_geometry(tmp_path / "half", subject, every=every, samples=2000)["mean"]
    assert half["normal_consistency"] < full["normal_consistency"] - 0.05


def test_a_point_set_drawn_as_surfels_is_scored_as_drawn(point_sets, tmp_path):
    """A point set exported as surfels (``surfel_min_cos``) has its normal maps splatted as
    surfels: with large points its outline stays near the GT head's where discs spill past it."""
    from safetensors.numpy import load_file

    from headforge.metrics.benchmark import (load_prediction, load_subject_gt, prediction_normals, render_normals,
                                             split_rows)

    subject = point_sets["subject"]
    arrays = load_file(str(point_sets["clean"] / "geometry.safetensors"))
    big = 3 * arrays["radius"]
    _write_points(tmp_path / "discs", arrays["frames"], arrays["points"], arrays["normals"], big)
    _write_points(tmp_path / "surfels", arrays["frames"], arrays["points"], arrays["normals"], big, surfel_min_cos=0.1)
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, "val", point_sets["every"])
    frames = gt["frames"][rows]
    K, R = np.asarray(info["intrinsics"]), int(info["resolution"])
    discs, surfels = (load_prediction(tmp_path / name, frames) for name in ("discs", "surfels"))
    assert discs.surfel_min_cos == 0 and surfels.surfel_min_cos == pytest.approx(0.1)
    head = np.isin(gt["labels"], info["head_labels"]) & point_sets["outer"]
    truth = (np.linalg.norm(render_normals(gt["vertices"][rows[0]], gt["faces"][head[gt["faces"]].all(1)], K, R), axis=-1) > 0.5).sum()
    covered = [(np.linalg.norm(prediction_normals(p, 0, K, R), axis=-1) > 0.5).sum() for p in (discs, surfels)]
    assert covered[0] > 1.05 * truth  # discs spill a radius past the outline
    assert abs(covered[1] - truth) < 0.5 * (covered[0] - truth)


def test_a_point_set_whose_renders_fill_holes_is_scored_with_them_filled(point_sets, tmp_path):
    """A sparse point set exported with ``hole_filling`` has the holes between its splats closed
    in its normal maps, as the avatar's renders close them: more of the GT head covered, within
    the GT outline's closure, and the added pixels' normals as good as the splatted ones."""
    from safetensors.numpy import load_file

    from headforge.metrics.benchmark import load_prediction, load_subject_gt, prediction_normals, split_rows

    subject = point_sets["subject"]
    arrays = load_file(str(point_sets["clean"] / "geometry.safetensors"))
    keep = np.random.default_rng(3).random(arrays["points"].shape[1]) < 0.2  # a fifth: holes open between the discs
    sparse = [arrays[k][:, keep] for k in ("points", "normals", "radius")]
    _write_points(tmp_path / "open", arrays["frames"], *sparse)
    _write_points(tmp_path / "filled", arrays["frames"], *sparse, hole_filling=True)
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, "val", point_sets["every"])
    K, R = np.asarray(info["intrinsics"]), int(info["resolution"])
    plain, filled = (load_prediction(tmp_path / name, gt["frames"][rows]) for name in ("open", "filled"))
    assert not plain.hole_filling and filled.hole_filling
    n_open, n_filled = (prediction_normals(p, 0, K, R) for p in (plain, filled))
    was, now = (np.linalg.norm(n, axis=-1) > 0.5 for n in (n_open, n_filled))
    added = now & ~was
    assert (was <= now).all() and np.allclose(n_filled[was], n_open[was], atol=1e-6)
    assert added.sum() > 0.01 * was.sum()  # the holes were there, and are filled
    assert np.allclose(np.linalg.norm(n_filled[added], axis=-1), 1, atol=1e-5)
    # an added pixel's normal is its neighbours': within a few degrees of the covered pixels next to it
    ys, xs = np.nonzero(added)
    near = np.stack([n_open[np.clip(ys + dy, 0, R - 1), np.clip(xs + dx, 0, R - 1)]
                     for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1)
    cos = np.einsum("pkc,pc->pk", near, n_filled[added])
    assert np.median(cos.max(1)) > 0.99


def test_a_point_set_with_its_own_regions_is_aligned_on_them(point_sets, tmp_path):
    """A point set placed 6 cm too deep (a point avatar inherits its tracking's depth error) that
    carries face_points / head_points is aligned by its own face points, back to ~the GT surface;
    with the camera-space GT labels instead, its "face points" are whatever lies nearest the GT
    face 6 cm away, and the alignment is off."""
    from safetensors.numpy import load_file

    from headforge.metrics.benchmark import evaluate_geometry, gt_point_labels, load_subject_gt, split_rows

    subject, every = point_sets["subject"], point_sets["every"]
    arrays = load_file(str(point_sets["clean"] / "geometry.safetensors"))
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, "val", every)
    _, _, _, label = gt_point_labels(arrays["points"][rows[0]], gt["vertices"][rows[0]], gt["faces"], gt["labels"])
    shifted = arrays["points"] + np.array([0.0, 0.0, 0.06], np.float32)
    _write_points(tmp_path / "gt_labels", arrays["frames"], shifted, arrays["normals"], arrays["radius"])
    own = tmp_path / "own"
    _write_points(own, arrays["frames"], shifted, arrays["normals"], arrays["radius"])
    with_regions = load_file(str(own / "geometry.safetensors")) | {
        "face_points": label == info["labels"]["face"], "head_points": np.isin(label, info["head_labels"])}
    save_file(with_regions, str(own / "geometry.safetensors"))
    m = evaluate_geometry(own, subject, every=every, samples=2000)["mean"]
    assert m["hausdorff_full_camera_mm"] > 20  # the shift itself
    assert m["hausdorff_face_mm"] < 1.0 and m["hausdorff_full_mm"] < 1.0 and m["normal_consistency"] > 0.96
    assert m["face_points"] == int((label == info["labels"]["face"])[np.random.default_rng(0).permutation(
        len(label))[:2000]].sum())
    by_gt = evaluate_geometry(tmp_path / "gt_labels", subject, every=every, samples=2000)["mean"]
    assert by_gt["face_points"] < m["face_points"] and by_gt["hausdorff_face_mm"] > m["hausdorff_face_mm"] + 1


def test_point_and_mesh_predictions_pair_either_way(point_sets, open_head_data, tmp_path):
    """``--reference`` with a point set on one side and a mesh on the other (the tracked head
    model, as PointAvatar against a mesh avatar), both ways round; each one's coverage reported."""
    from typer.testing import CliRunner

    from headforge.cli import app
    from headforge.metrics.benchmark import paired_normal_error

    subject, every = point_sets["subject"], point_sets["every"]
    one_way = paired_normal_error(point_sets["clean"], subject, subject, every=every)["mean"]
    other_way = paired_normal_error(subject, point_sets["clean"], subject, every=every)["mean"]
    assert one_way["common_coverage"] == pytest.approx(other_way["common_coverage"])
    assert one_way["coverage"] == pytest.approx(other_way["reference_coverage"])
    assert one_way["normal_error_head_deg"] == pytest.approx(other_way["reference_normal_error_head_deg"])
    assert 0.5 < one_way["reference_coverage"] <= 1 and one_way["common_coverage"] <= one_way["coverage"]
    res = CliRunner().invoke(app, ["eval", str(point_sets["clean"]), str(subject), "--reference", str(subject),
                                   "--every", str(every), "--json", "-o", str(tmp_path / "eval")])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output.strip().splitlines()[-1])
    assert summary["kind"] == "points" and summary["frames"] == 1
    assert summary["paired_coverage"] == pytest.approx(summary["head_coverage"])
    assert summary["paired_reference_coverage"] == pytest.approx(one_way["reference_coverage"])
    assert (tmp_path / "eval" / "views.png").is_file() and (tmp_path / "eval" / "normal_error.png").is_file()
    assert "(points)" in (tmp_path / "eval" / "metrics.md").read_text()


class _PointAvatar:
    """What export_geometry reads of an avatar: per-frame parameters and ``geometry``."""

    def __init__(self, T: int, P: int, radius_shape: str = "per point", surfel_min_cos: float = 0.0,
                 hole_filling: bool = False):
        self.frames = {"translation": torch.zeros(T, 3)}
        self.P, self.radius_shape, self.surfel_min_cos, self.hole_filling = P, radius_shape, surfel_min_cos, hole_filling

    def frame_params(self, rows):
        return {"rows": rows}

    def geometry(self, params):
        from headforge.avatars.base import Geometry

        rows = params["rows"].double()
        B = len(rows)
        pts = torch.linspace(0, 1, self.P * 3).reshape(1, self.P, 3) + rows[:, None, None]
        pts = pts.float() + torch.tensor([0.0, 0.0, 1.0])
        normals = torch.nn.functional.normalize(pts.flip(-1) - 0.3, dim=-1)
        radius = 1e-3 * (1 + rows[:, None].float()).expand(B, self.P) if self.radius_shape == "per point" \
            else torch.full((self.P,), 2e-3)
        # strided views, as a model's outputs may be: the export must still write them correctly
        return Geometry(pts.transpose(0, 1).contiguous().transpose(0, 1), normals=normals,
                        radius=radius, surfel_min_cos=self.surfel_min_cos, hole_filling=self.hole_filling)


@pytest.mark.parametrize("radius_shape, surfel_min_cos, hole_filling", [("per point", 0.0, False),
                                                                       ("shared (P,)", 0.25, True)])
def test_the_engine_exports_a_point_avatar_as_a_point_set(point_sets, tmp_path, radius_shape, surfel_min_cos,
                                                          hole_filling):
    from safetensors.numpy import load_file

    from headforge.avatars.engine import export_geometry
    from headforge.metrics.benchmark import exported_geometry

    subject = point_sets["subject"]
    gt_frames = load_file(str(subject / "gt" / "geometry.safetensors"))["frames"]
    avatar = _PointAvatar(T=int(gt_frames.max()), P=50, radius_shape=radius_shape,  # the last GT frame is beyond T
                          surfel_min_cos=surfel_min_cos, hole_filling=hole_filling)
    export_geometry(avatar, subject, tmp_path / "geometry.safetensors")
    assert not list(tmp_path.glob("*.tmp.*"))
    loaded = exported_geometry(tmp_path)
    kept = gt_frames[gt_frames < avatar.frames["translation"].shape[0]]
    assert loaded.is_points and np.array_equal(loaded.frames, kept)
    want = avatar.geometry(avatar.frame_params(torch.from_numpy(kept)))
    assert np.allclose(loaded.vertices, want.vertices.numpy())
    assert np.allclose(loaded.normals, want.normals.numpy(), atol=1e-6)
    assert loaded.radius.shape == (len(kept), 50)
    assert np.allclose(loaded.radius, want.radius.expand(len(kept), 50).numpy())
    assert loaded.surfel_min_cos == pytest.approx(surfel_min_cos)
    assert loaded.hole_filling == hole_filling


def test_a_point_avatar_without_normals_or_radius_is_refused_at_export(point_sets, tmp_path):
    from headforge.avatars.base import Geometry
    from headforge.avatars.engine import export_geometry

    avatar = _PointAvatar(T=4, P=5)
    avatar.geometry = lambda params: Geometry(torch.zeros(len(params["rows"]), 5, 3))
    with pytest.raises(HeadforgeError, match="normals and radius"):
        export_geometry(avatar, point_sets["subject"], tmp_path / "geometry.safetensors")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("damage, message", [
    ("no radius", "lacks 'radius'"),
    ("no points or vertices", "lacks 'vertices' (a mesh) or 'points' (a point set)"),
    ("normals (T, P, 2)", "are not (T,), (T, P, 3), (T, P, 3) and (T, P)"),
    ("radius (T, P + 1)", "are not (T,), (T, P, 3), (T, P, 3) and (T, P)"),
    ("one frame too few", "are not (T,), (T, P, 3), (T, P, 3) and (T, P)"),
    ("no points", "P >= 1"),
    ("nan point", "must be finite"),
    ("zero normal", "zero length"),
    ("negative radius", "radius must be positive"),
    ("float frames", "integer frame indices"),
    ("face_points (P + 1,)", "point masks"),
    ("face_points without head_points", "lacks 'head_points'"),
    ("surfel_min_cos 0", "surfel_min_cos must be one value in (0, 1]"),
    ("surfel_min_cos (2,)", "surfel_min_cos must be one value in (0, 1]"),
    ("hole_filling 2", "hole_filling must be one value, 0 or 1"),
])
def test_a_bad_point_file_is_one_line_error(tmp_path, damage, message):
    from headforge.metrics.benchmark import load_prediction

    T, P = 3, 4
    arrays = {"frames": np.arange(T), "points": np.ones((T, P, 3), np.float32),
              "normals": np.ones((T, P, 3), np.float32), "radius": np.full((T, P), 1e-3, np.float32)}
    if damage == "no radius":
        del arrays["radius"]
    elif damage == "no points or vertices":
        del arrays["points"]
    elif damage == "normals (T, P, 2)":
        arrays["normals"] = arrays["normals"][..., :2].copy()
    elif damage == "radius (T, P + 1)":
        arrays["radius"] = np.full((T, P + 1), 1e-3, np.float32)
    elif damage == "one frame too few":
        arrays["frames"] = np.arange(T - 1)
    elif damage == "no points":
        arrays |= {"points": np.ones((T, 0, 3), np.float32), "normals": np.ones((T, 0, 3), np.float32),
                   "radius": np.ones((T, 0), np.float32)}
    elif damage == "nan point":
        arrays["points"][1, 2, 0] = np.nan
    elif damage == "zero normal":
        arrays["normals"][0, 0] = 0
    elif damage == "negative radius":
        arrays["radius"][2, 3] = -1e-3
    elif damage == "float frames":
        arrays["frames"] = np.arange(T, dtype=np.float32)
    elif damage == "face_points (P + 1,)":
        arrays |= {"face_points": np.ones(P + 1, bool), "head_points": np.ones(P, bool)}
    elif damage == "face_points without head_points":
        arrays["face_points"] = np.ones(P, bool)
    elif damage == "surfel_min_cos 0":
        arrays["surfel_min_cos"] = np.zeros(1, np.float32)
    elif damage == "surfel_min_cos (2,)":
        arrays["surfel_min_cos"] = np.full(2, 0.5, np.float32)
    elif damage == "hole_filling 2":
        arrays["hole_filling"] = np.array([2], np.uint8)
    save_file(arrays, str(tmp_path / "geometry.safetensors"))
    with pytest.raises(HeadforgeError) as err:
        load_prediction(tmp_path, np.arange(T))
    text = str(err.value)
    assert message in text and "\n" not in text and str(tmp_path / "geometry.safetensors") in text
