"""headforge synth: motion, geometry, renders, dataset format and the geometry evaluation."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from safetensors.numpy import load_file

from headforge.bench import synthetic as S
from headforge.errors import HeadforgeError


@pytest.fixture(scope="module")
def anny_model():
    return S.load_anny()


@pytest.fixture(scope="module")
def bench(synth_bench):
    return synth_bench


def test_talking_sequences_stay_in_range_blink_and_differ(anny_model):
    labels = list(anny_model.facial_action_labels)
    acts, rot = S.talking_sequence(labels, 300, seed=3, validation=False)
    acts_v, rot_v = S.talking_sequence(labels, 300, seed=3, validation=True)
    assert acts.shape == (300, 52) and rot.shape == (300, 3)
    assert acts.min() >= 0 and acts.max() <= 1
    assert np.abs(np.degrees(rot)).max(0).tolist() <= [15.0 + 1e-6, 30.0 + 1e-6, 5.0 + 1e-6]
    assert np.degrees(np.abs(rot[:, 1])).max() > 10  # the head really turns
    blink = labels.index("eyeBlinkLeft")
    assert (acts[:, blink] >= 1.0).sum() >= 2  # several full blinks in 12 s
    assert acts[:, labels.index("jawOpen")].max() > 0.2
    used_train = set(np.nonzero(acts.max(0) > 0.05)[0])
    used_val = set(np.nonzero(acts_v.max(0) > 0.05)[0])
    assert used_val - used_train  # validation shows expressions training never does


def test_hair_is_a_closed_shell_outside_the_skin(anny_model):
    import trimesh

    subject = S.sample_subject(anny_model, 2, seed=0)  # bun
    config = S.SynthConfig(hair_voxel_m=0.006)
    sm, _ = S.build_subject_mesh(anny_model, subject, config)
    hair = trimesh.Trimesh(sm.hair_vertices, sm.hair_faces, process=False)
    assert hair.is_watertight and hair.volume > 0  # outward winding
    assert subject.hair_style == "bun"
    # hair sits on the scalp: above the eyes, and no hair vertex deep inside the body
    assert np.median(sm.hair_vertices[:, 1]) > 0.0
    body = trimesh.Trimesh(np.asarray(S.pose_subject(anny_model, sm, _, np.zeros((1, 52)), np.zeros((1, 3)))[0][:len(sm.keep)]),
                           sm.faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(body, sm.hair_vertices[::20])
    assert np.percentile(dist, 95) < 0.06


def test_synth_writes_a_tracked_dataset_with_consistent_ground_truth(bench):
    from headforge.data.dataset import HeadDataset

    out, config, report = bench
    subject = out / "subject_00"
    assert (out / "contact_sheet.png").is_file() and (out / "benchmark.json").is_file()
    assert not out.with_name("bench.partial").exists()
    train, val = HeadDataset(subject, "train"), HeadDataset(subject, "val")
    assert len(train) + len(val) == report["subjects"][0]["frames_valid"] and len(val) <= 6
    item = train[0]
    assert item["image"].shape == (224, 224, 3)
    meta = json.loads((subject / "dataset.json").read_text())
    assert meta["synthetic"]["gt"] == "gt/"
    assert meta["fps"] == S.FPS == 25.0  # the rate the talking sequence is sampled at, not the folder default
    assert abs(meta["intrinsics"][0][0] - config.focal_factor * 224) < 1e-3  # known focal (float32) passed on
    info = json.loads((subject / "gt/subject.json").read_text())
    geo = load_file(str(subject / "gt/geometry.safetensors"))
    assert geo["frames"].tolist() == list(range(0, 16, 2))
    # GT geometry projects onto the rendered mask; head labels sit inside it
    K = np.asarray(info["intrinsics"])
    f = 12  # a validation frame with full GT
    v = geo["vertices"][list(geo["frames"]).index(f)]
    uv = (v[:, :2] / v[:, 2:]) * K[0, 0] + K[0, 2]
    mask = cv2.imread(str(subject / f"masks/{f:05d}.png"), 0) / 255.0
    head = np.isin(geo["labels"], [1, 2])
    px = np.round(uv[head]).astype(int)
    inside = (px >= 0).all(1) & (px < 224).all(1)
    assert mask[px[inside, 1], px[inside, 0]].mean() > 0.95
    labels = cv2.imread(str(subject / f"gt/labels/{f:05d}.png"), 0)
    assert ((labels > 0) == (mask > 0.5)).mean() > 0.97
    normals = cv2.imread(str(subject / f"gt/normals/{f:05d}.png"), -1)[..., ::-1] / 255.0 * 2 - 1
    n = np.linalg.norm(normals[labels > 0], axis=-1)
    assert np.median(np.abs(n - 1)) < 0.02
    face_n = normals[labels == S.LABELS["face"]]
    assert np.median(face_n[:, 2]) < -0.5  # face normals look back at the camera (OpenCV: -z)
    for name in (f"gt/albedo/{f:05d}.png", f"gt/relit/{f:05d}.png", f"gt/views/{f:05d}_yaw+20.png"):
        assert (subject / name).is_file(), name
    relit = cv2.imread(str(subject / f"gt/relit/{f:05d}.png"))
    frame = cv2.imread(str(subject / f"frames/{f:05d}.png"))
    assert np.abs(relit.astype(float) - frame).mean() > 3  # another light really changes the image


def test_synth_writes_gt_landmarks_and_the_training_frames_normal_and_label_maps(bench):
    """Every training frame has its normal and label maps (NHA's GT supervision); validation
    frames only the GT frames'. The GT landmarks (open-head's embedded points on the subject's
    surface, projected) agree with MediaPipe's detections on the renders to a detector's error,
    and they move with the face, frame to frame, as the detections do."""
    from headforge.data.dataset import load_tracking, read_meta

    out, config, _ = bench
    subject = out / "subject_00"
    for f in range(config.train_frames):
        assert (subject / f"gt/normals/{f:05d}.png").is_file() and (subject / f"gt/labels/{f:05d}.png").is_file()
    val_maps = sorted(int(p.stem) for p in (subject / "gt/normals").glob("*.png") if int(p.stem) >= config.train_frames)
    assert val_maps == [f for f in range(config.train_frames, 16) if f % config.gt_every == 0]
    gt = load_file(str(subject / "gt/landmarks.safetensors"))
    assert gt["landmarks"].shape == (16, 478, 2) and gt["frames"].tolist() == list(range(16))
    meta = read_meta(subject)
    detected = load_tracking(subject, meta)["landmarks"].numpy()
    valid = [r["index"] for r in meta["frames"] if r["valid"]]
    error = np.linalg.norm(gt["landmarks"][valid] - detected[valid], axis=-1)
    assert np.nanmedian(error) < 3.0  # px at 224 (1.7 measured): MediaPipe's own error on these renders
    # the head turns by ~30 px at 224 over these frames: the GT follows the detections' path
    path_gt, path_detected = gt["landmarks"][valid].mean(1), np.nanmean(detected[valid], 1)
    assert np.ptp(path_gt[:, 0]) > 10
    assert np.corrcoef(path_gt[:, 0], path_detected[:, 0])[0, 1] > 0.99


def test_geometry_eval_of_the_tracked_baseline(bench, open_head_data):
    from headforge.metrics.benchmark import evaluate_geometry

    out, _, _ = bench
    subject = out / "subject_00"
    result = evaluate_geometry(subject, subject, split="val", samples=2000)
    assert result["frames"] == 3 and result["frames_available"] == 3
    m = result["mean"]
    assert 3 < m["normal_error_head_deg"] < 40
    assert 0.3 < m["hausdorff_face_mm"] < 8  # tracked face within millimetres after alignment
    assert m["hausdorff_face_mm"] <= m["hausdorff_face_camera_mm"] + 0.5
    # a free scale can only bring the face closer; a tracked head is within a quarter of its size
    assert m["hausdorff_face_scaled_mm"] <= m["hausdorff_face_mm"] + 0.3 and 0.8 < m["alignment_scale"] < 1.25
    assert 0.7 < m["normal_consistency"] <= 1
    # the bald head model lies under the short hair: farther from the outer surface alone
    assert m["hausdorff_full_outer_mm"] > m["hausdorff_full_mm"]
    assert 0.5 < m["head_coverage"] < 1  # the hair the head model lacks is left uncovered
    # turntable views: GT on top, prediction below, turned alike (the tracked head sits on the GT)
    R = int(json.loads((subject / "gt" / "subject.json").read_text())["resolution"])
    views = result["views"]
    assert views.shape == (2 * R, 4 * R, 3)
    drawn = np.abs(views - 0.5).sum(-1) > 1e-3
    for k in range(4):
        gt_px, pred_px = drawn[:R, k * R:(k + 1) * R], drawn[R:, k * R:(k + 1) * R]
        assert pred_px.any() and (gt_px & pred_px).sum() > 0.8 * pred_px.sum()
    assert not np.array_equal(drawn[R:, :R], drawn[R:, 2 * R:3 * R])  # the views really turn


def test_paired_normal_error_scores_two_predictions_on_the_pixels_both_cover(bench, open_head_data, tmp_path):
    """The tracked head with everything but its face cut away, against the whole tracked head:
    on their common pixels both show the same surface, so their errors agree; the common pixels
    are the face-only prediction's coverage, and its own-coverage error is what the pair reports."""
    from safetensors.numpy import save_file

    from headforge.metrics.benchmark import (evaluate_geometry, load_subject_gt, paired_normal_error,
                                             split_rows, tracked_geometry)

    out, _, _ = bench
    subject = out / "subject_00"
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, "val", 1)
    whole = tracked_geometry(subject, gt["frames"][rows])
    face_only = tmp_path / "face_only"
    face_only.mkdir()
    save_file({"frames": whole.frames, "vertices": whole.vertices.astype(np.float32),
               "faces": whole.faces[whole.face_vertices[whole.faces].all(1)].astype(np.int64),
               "face_vertices": whole.face_vertices, "head_vertices": whole.head_vertices},
              str(face_only / "geometry.safetensors"))
    pair = paired_normal_error(face_only, subject, subject)
    own = evaluate_geometry(face_only, subject, samples=500)["mean"]
    whole_own = evaluate_geometry(subject, subject, samples=500)["mean"]
    m = pair["mean"]
    assert pair["frames"] == len(rows)
    assert abs(m["normal_error_head_deg"] - m["reference_normal_error_head_deg"]) < 0.05
    assert abs(m["normal_error_face_deg"] - m["reference_normal_error_face_deg"]) < 0.05
    assert abs(m["normal_error_head_deg"] - own["normal_error_head_deg"]) < 0.05
    assert abs(m["common_coverage"] - own["head_coverage"]) < 1e-6
    assert m["common_coverage"] < whole_own["head_coverage"] - 0.1  # the face alone covers far less
    # the reference's own error (on its own, larger coverage) is not what the pair reports for it
    assert abs(m["reference_normal_error_head_deg"] - whole_own["normal_error_head_deg"]) > 0.1
    # headforge eval --reference adds the pair to the report
    from typer.testing import CliRunner

    from headforge.cli import app

    res = CliRunner().invoke(app, ["eval", str(face_only), str(subject), "--reference", str(subject), "--json",
                                   "-o", str(tmp_path / "eval")])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output.strip().splitlines()[-1])
    assert abs(summary["paired_reference_normal_error_head_deg"] - m["reference_normal_error_head_deg"]) < 1e-6
    assert "paired_common_coverage" in json.loads((tmp_path / "eval" / "metrics.json").read_text())["mean"]
    # a --reference that is no prediction, or one for image folders, is refused before any report is written
    empty = tmp_path / "empty"
    empty.mkdir()
    for gt, message in ((subject, "neither tracking.safetensors nor geometry.safetensors"), (empty, "--reference needs")):
        res = CliRunner().invoke(app, ["eval", str(face_only), str(gt), "--reference", str(empty),
                                       "-o", str(tmp_path / "refused")])
        assert res.exit_code != 0 and message in str(res.exception)
        assert not (tmp_path / "refused").exists()


def test_normal_error_by_label_adds_up_to_the_full_head_figure(bench, open_head_data):
    """The per-label split of the tracked model's full-head normal error: on one frame the shares
    weight the labels' errors back to evaluate_geometry's figure; the bald model covers the face
    but not all of the hair; the GT meshes scored as a prediction sit at the renderer's floor."""
    from headforge.metrics.benchmark import evaluate_geometry, load_subject_gt, normal_error_by_label, split_rows

    out, _, _ = bench
    subject = out / "subject_00"
    gt, info = load_subject_gt(subject)
    rows, _ = split_rows(gt, info, subject, "val", 1)
    one = len(rows)  # every = the frame count: the first GT frame alone
    split = normal_error_by_label(subject, subject, every=one)
    assert set(split) == {name for name, value in info["labels"].items() if value in info["head_labels"]}
    assert abs(sum(r["share"] for r in split.values()) - 1) < 1e-9
    pooled = sum(r["share"] * r["deg"] for r in split.values())
    protocol = evaluate_geometry(subject, subject, every=one, samples=200)["mean"]["normal_error_head_deg"]
    assert abs(pooled - protocol) < 0.01
    assert split["face"]["covered"] > 0.95 and split["hair"]["covered"] < split["face"]["covered"]
    floor = normal_error_by_label(None, subject, every=one)
    assert floor["face"]["deg"] < 2 and floor["face"]["covered"] > 0.99 and floor["hair"]["covered"] > 0.95
    assert floor["face"]["deg"] < split["face"]["deg"] / 2


def test_outer_surface_drops_the_scalp_under_the_hair_and_the_hair_shell_inside_the_skin():
    """A unit-sphere head whose top is covered by a closed hair volume from r = 0.98 (under the
    skin) to r = 1.2 above z = 0.31: only the outer hair cap, its rim and the bare lower skin are outer."""
    import trimesh
    from skimage.measure import marching_cubes

    from headforge.metrics.benchmark import outer_surface_faces
    from headforge.metrics.geometry import one_sided_hausdorff

    head = trimesh.creation.icosphere(subdivisions=4)
    step = 0.04  # the hair volume meshed like the synth's: marching cubes of its SDF, closed by padding
    axis = np.arange(-1.4, 1.4 + step / 2, step)
    g = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1)
    r = np.linalg.norm(g, axis=-1)
    sdf = np.pad(np.maximum(np.maximum(r - 1.2, 0.98 - r), 0.31 - g[..., 2]), 1, constant_values=1.0)
    hv, hf, _, _ = marching_cubes(sdf, level=0.0, spacing=(step,) * 3)
    hair = max(trimesh.Trimesh(hv + axis[0] - step, hf, process=True).split(only_watertight=False),
               key=lambda m: len(m.faces))  # as build_hair: the main part, not 2-face slivers
    if hair.volume < 0:
        hair.invert()
    assert hair.is_watertight
    vertices = np.concatenate([head.vertices, hair.vertices])
    faces = np.concatenate([head.faces, hair.faces + len(head.vertices)])
    labels = np.concatenate([np.full(len(head.vertices), 2), np.full(len(hair.vertices), 3)])
    keep = outer_surface_faces(vertices, faces, labels, hair_label=3)
    centres = vertices[faces].mean(1)
    r, z = np.linalg.norm(centres, axis=1), centres[:, 2]
    is_hair = np.arange(len(faces)) >= len(head.faces)
    assert not keep[~is_hair & (z > 0.35)].any()  # scalp under the hair
    assert keep[~is_hair & (z < 0.25)].all()  # bare skin
    assert not keep[is_hair & (r < 0.99) & (z > 0.35)].any()  # the hair's inner shell
    assert keep[is_hair & (r > 1.19)].all()  # the hair's outer surface
    # a bald prediction (the unit sphere) is near the hidden surfaces, ~the hair depth from the outer one
    bald_top = head.faces[head.triangles_center[:, 2] > 0.5]
    to_all = one_sided_hausdorff(head.vertices, bald_top, vertices, faces, samples=2000)["mean"]
    to_outer = one_sided_hausdorff(head.vertices, bald_top, vertices, faces[keep], samples=2000)["mean"]
    assert to_all < 0.01 and 0.15 < to_outer < 0.21


def test_geometry_eval_refuses_bad_inputs(bench, tmp_path):
    from headforge.metrics.benchmark import evaluate_geometry

    out, _, _ = bench
    subject = out / "subject_00"
    with pytest.raises(HeadforgeError, match="not a headforge synth subject"):
        evaluate_geometry(subject, tmp_path)
    with pytest.raises(HeadforgeError, match="neither tracking.safetensors nor geometry.safetensors"):
        evaluate_geometry(tmp_path, subject)
    with pytest.raises(HeadforgeError, match="split must be"):
        evaluate_geometry(subject, subject, split="test")


def test_synth_config_errors():
    with pytest.raises(HeadforgeError, match="--resolution"):
        S.SynthConfig(resolution=32).validate()
    with pytest.raises(HeadforgeError, match="--gt-every"):
        S.SynthConfig(gt_every=0).validate()
