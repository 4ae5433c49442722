"""HeadCraft scan sets (generated, with ground truth) and the external scan reader."""

import json
from pathlib import Path

import numpy as np
import pytest

from headforge.errors import HeadforgeError

SCANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "scans"


@pytest.fixture(scope="module")
def data():
    from headforge.head.open_head import load_open_head

    return load_open_head()


def test_clean_set_is_fast_and_labelled(tmp_path):
    from headforge.craft.scans import (
        LABELS,
        ScanSetConfig,
        generate_scans,
        load_generated,
    )

    keys = generate_scans(tmp_path, ScanSetConfig(n=2, source="open-head", harder=False, expression_every=2,
                                                  hair_voxel_m=0.009, sheet_px=48), log=lambda m: None)
    assert keys == ["id000", "id001", "id001_expr"]
    scan, spec, gt = load_generated(tmp_path / "id001")
    assert spec["variant"] == "clean" and spec["hair_style"] == "short"
    assert set(np.unique(gt["labels"])) >= {LABELS["face"], LABELS["hair"], LABELS["eyes"]}
    assert gt["head"].shape[1] == 3 and gt["landmarks"].shape == (478, 3)
    expr = np.load(tmp_path / "id001_expr" / "gt.npz")
    assert np.abs(expr["head"] - gt["head"]).max() > 2e-3  # the expression scan differs from the neutral one


def test_worker_processes_make_the_same_set(tmp_path):
    from headforge.craft.scans import ScanSetConfig, generate_scans

    cfg = ScanSetConfig(n=2, source="open-head", harder=False, expression_every=2, hair_voxel_m=0.009, sheet_px=48)
    serial = generate_scans(tmp_path / "serial", cfg, log=lambda m: None)
    lines = []
    parallel = generate_scans(tmp_path / "parallel", cfg, log=lines.append, workers=2)
    assert parallel == serial and len(lines) == 3 and not list((tmp_path / "parallel").glob("*.partial"))
    for key in serial:
        a, b = (np.load(tmp_path / side / key / "gt.npz") for side in ("serial", "parallel"))
        assert np.array_equal(a["head"], b["head"]) and np.array_equal(a["labels"], b["labels"])
        assert ((tmp_path / "serial" / key / "gt.json").read_text()
                == (tmp_path / "parallel" / key / "gt.json").read_text())
    with pytest.raises(HeadforgeError, match="--workers"):
        generate_scans(tmp_path / "bad", cfg, workers=0)


@pytest.mark.slow  # ~2 min on 2 busy cores (the remeshed variant)
def test_generated_set_ground_truth_and_resume(tmp_path):
    from headforge.craft.scans import (
        LABELS,
        ScanSetConfig,
        generate_scans,
        load_generated,
    )
    from headforge.metrics.geometry import points_to_mesh

    cfg = ScanSetConfig(n=2, source="open-head", expression_every=2, hair_voxel_m=0.005, remesh_voxel_m=0.004,
                        sheet_px=96)
    keys = generate_scans(tmp_path, cfg, log=lambda m: None)
    assert keys == ["id000", "id001", "id001_expr"]
    assert (tmp_path / "contact_sheet.png").exists() and not list(tmp_path.glob("*.partial*"))
    bald, spec0, gt0 = load_generated(tmp_path / "id000")
    short, spec1, gt1 = load_generated(tmp_path / "id001")
    assert (spec0["hair_style"], spec0["variant"]) == ("bald", "clean")
    assert (spec1["hair_style"], spec1["variant"]) == ("short", "remeshed")
    assert json.loads((tmp_path / "id001_expr" / "gt.json").read_text())["expression"]
    assert not gt0["hair"].any() and 0.1 < gt1["hair"].mean() < 0.7
    assert gt1["labels"].shape == (len(short.vertices),) and LABELS["face"] in gt1["labels"]
    # landmarks lie on the scan's skin; the remeshed scan is watertight
    d = points_to_mesh(gt0["landmarks"], bald.vertices, bald.faces)
    assert np.median(d) < 1e-4
    import trimesh

    assert trimesh.Trimesh(short.vertices, short.faces, process=False).is_watertight
    assert len(short.vertices) != len(bald.vertices)
    # the scan is the canonical head moved by (R, t)
    R, t = np.array(spec0["rotation"]), np.array(spec0["translation"])
    assert not np.allclose(R, np.eye(3)) and np.allclose(R @ R.T, np.eye(3), atol=1e-6)
    eyes = ((gt0["landmarks"] - t) @ R)[[33, 263]].mean(0)  # canonical origin: between the eyes
    assert abs(eyes[0]) < 0.005 and abs(eyes[1]) < 0.015
    before = (tmp_path / "id001" / "scan.ply").stat().st_mtime_ns
    assert generate_scans(tmp_path, cfg, log=lambda m: None) == keys
    assert (tmp_path / "id001" / "scan.ply").stat().st_mtime_ns == before  # resumed, not redone


@pytest.mark.parametrize("style", ["long", "ponytail", "curly"])
def test_hair_styles(style, data):
    from headforge.craft.scans import build_hair_volume

    v, f = data.v_template, data.faces
    hv, hf, sdf = build_hair_volume(style, v, f, data.regions["scalp"], 0.006, seed=0)
    assert len(hf) > 500
    assert sdf(v[data.regions["scalp"]]).mean() < 0  # the scalp is under the hair
    assert sdf(v[data.regions["face"]]).mean() > 0  # the face is not
    if style == "ponytail":
        assert hv[:, 2].min() < v[:, 2].min() - 0.02  # the tail sticks out behind the head
    if style == "long":
        assert hv[:, 1].min() < -0.12  # down below the jaw


def test_banded_grid_values_match_the_full_evaluation_near_the_surface():
    from headforge.craft.scans import banded_grid_values, full_grid_values

    axes = [np.linspace(-0.1, 0.1, 41), np.linspace(-0.1, 0.12, 45), np.linspace(-0.1, 0.1, 40)]
    calls = []

    def sphere(p):
        calls.append(len(p))
        return np.linalg.norm(p - 0.01, axis=1) - 0.06

    full = full_grid_values(axes, sphere)
    calls.clear()
    band = banded_grid_values(axes, sphere, margin=0.02)
    near = np.abs(full) < 0.01
    assert np.array_equal(band[near], full[near])  # exact near the zero level
    assert np.array_equal(np.sign(band), np.sign(full))
    assert np.abs(band - full).max() < 0.005  # interpolated elsewhere
    assert sum(calls) < 0.6 * full.size  # and fewer evaluations


@pytest.mark.parametrize("style", ["bob", "bun"])
def test_banded_hair_volume_is_the_full_one(style, data, monkeypatch):
    from headforge.craft import scans

    v, f, scalp = data.v_template, data.faces, data.regions["scalp"]
    banded = scans.build_hair_volume(style, v, f, scalp, 0.006, seed=0)
    monkeypatch.setattr(scans, "banded_grid_values", lambda axes, evaluate, margin: scans.full_grid_values(axes, evaluate))
    full = scans.build_hair_volume(style, v, f, scalp, 0.006, seed=0)
    assert np.array_equal(banded[0], full[0]) and np.array_equal(banded[1], full[1])


def test_bald_has_no_hair(data):
    from headforge.craft.scans import build_hair_volume

    assert build_hair_volume("bald", data.v_template, data.faces, data.regions["scalp"], 0.006, 0) == (None, None, None)
    with pytest.raises(HeadforgeError, match="unknown hair style"):
        build_hair_volume("mohawk", data.v_template, data.faces, data.regions["scalp"], 0.006, 0)


def test_reader_units_axes_and_bad_files(tmp_path, data):
    import trimesh

    from headforge.craft.scans import read_scan

    mesh = trimesh.Trimesh(data.v_template * 1000, data.faces, process=False)  # millimetres
    # stored z-up, face toward -y (anny's axes)
    mesh.vertices = np.asarray(mesh.vertices) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]).T
    mesh.export(tmp_path / "head.stl")
    scan = read_scan(tmp_path / "head.stl", units="auto", up="+z", forward="-y")
    assert scan.meta["units"] == "mm"
    from scipy.spatial import cKDTree

    assert cKDTree(data.v_template).query(scan.vertices)[0].max() < 1e-5  # STL keeps corners unwelded
    (tmp_path / "empty.obj").write_text("# nothing\n")
    with pytest.raises(HeadforgeError, match="empty"):
        read_scan(tmp_path / "empty.obj")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n")
    with pytest.raises(HeadforgeError, match="degenerate"):
        read_scan(tmp_path / "flat.obj")
    (tmp_path / "x.xyz").write_text("1 2 3\n")
    with pytest.raises(HeadforgeError, match="unsupported"):
        read_scan(tmp_path / "x.xyz")
    with pytest.raises(HeadforgeError, match="different axes"):
        read_scan(tmp_path / "head.stl", up="+y", forward="-y")


@pytest.mark.skipif(not (SCANS / "james.ljson").exists(), reason="real scans not present")
def test_menpo_ljson_landmarks():
    from headforge.craft.scans import read_scan

    scan = read_scan(SCANS / "james.obj", landmarks=SCANS / "james.ljson")
    lmk = scan.landmarks
    assert scan.meta["units"] == "mm" and np.isfinite(lmk).all(1).sum() == 51
    # subject's left eye (MediaPipe 263) is at +x, the right (33) at -x; the nose in front
    assert lmk[263, 0] > lmk[33, 0] + 0.06
    assert lmk[4, 2] > lmk[[33, 263], 2].mean() + 0.01
