"""HeadCraft registration: landmark alignment, the two stages, bad scans, the batch command."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from headforge.errors import HeadforgeError

SCANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "scans"


@pytest.fixture(scope="module")
def template():
    from headforge.craft import pipeline

    return pipeline.template_for("open-head", 1)


@pytest.fixture(scope="module")
def bald_set(tmp_path_factory):
    """One clean bald in-span scan (instant to make)."""
    from headforge.craft.scans import ScanSetConfig, generate_scans

    folder = tmp_path_factory.mktemp("bald")
    generate_scans(folder, ScanSetConfig(n=1, source="open-head", expression_every=9, sheet_px=64), log=lambda m: None)
    return folder


@pytest.fixture(scope="module")
def scan_set(tmp_path_factory):
    """Two in-span (open-head source) scans: id000 bald clean, id001 short hair remeshed (5 mm)."""
    from headforge.craft.scans import ScanSetConfig, generate_scans

    folder = tmp_path_factory.mktemp("scans")
    generate_scans(folder, ScanSetConfig(n=2, source="open-head", expression_every=9, hair_voxel_m=0.005,
                                         remesh_voxel_m=0.004, sheet_px=64), log=lambda m: None)
    return folder


def _fast(config):
    config.landmark_steps = 120
    config.scan_points = 15_000
    config.stage1 = replace(config.stage1, steps=120)
    config.stage2 = replace(config.stage2, steps=60)
    return config


def test_umeyama_recovers_similarity():
    from scipy.spatial.transform import Rotation

    from headforge.craft.register import umeyama

    rng = np.random.default_rng(0)
    src = rng.normal(size=(40, 3))
    R = Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix()
    s, R2, t = umeyama(src, 1.3 * src @ R.T + [1, 2, 3])
    assert abs(s - 1.3) < 1e-9 and np.allclose(R2, R) and np.allclose(t, [1, 2, 3])


def test_prune_schedule_coarse_to_fine():
    from headforge.craft.register import StageConfig

    fixed = StageConfig(steps=100, lr=1e-2, chamfer=1, edge=1, laplacian=1, prune_units=3.0)
    assert {fixed.prune_at(k) for k in (0, 50, 99)} == {3.0}
    ramp = replace(fixed, prune_start_units=12.0, prune_decay=0.5)
    assert ramp.prune_at(0) == pytest.approx(12.0)
    assert ramp.prune_at(25) == pytest.approx(6.0)  # geometric: halfway in log space
    assert ramp.prune_at(50) == pytest.approx(3.0) and ramp.prune_at(99) == pytest.approx(3.0)
    assert all(ramp.prune_at(k) >= ramp.prune_at(k + 1) for k in range(99))


def test_correspondences_refresh_every_nn_every_steps(monkeypatch):
    """Both directions' nearest neighbours are queried only on refresh steps (the quick preset's
    speed-up); in between the distances follow the moving template with the cached pairs."""
    import scipy.spatial
    import torch

    from headforge.craft import register as R

    queries = []

    class CountingTree(scipy.spatial.cKDTree):
        def query(self, *args, **kwargs):
            queries.append(1)
            return super().query(*args, **kwargs)

    monkeypatch.setattr(scipy.spatial, "cKDTree", CountingTree)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    scan = np.random.default_rng(0).normal(size=(50, 3)) * 0.01
    losses = R.Losses(faces, 4, scan, replace(R.RegisterConfig.quick(), nn_every=4))
    x = torch.as_tensor(scan[:4] * R.PAPER_UNITS_PER_M, dtype=torch.float64)
    terms = [losses.chamfer(x + 0.1 * step, step, prune=100.0)[0] for step in range(8)]
    assert len(queries) == 4  # steps 0 and 4, two directions each
    assert float(terms[1]) != float(terms[0])  # the cached pairs, the moved template


def test_outer_face_is_the_face_beyond_the_inner_landmarks(template):
    import torch
    from scipy.spatial import cKDTree

    from headforge.craft import register as R
    from headforge.head.landmarks import FACE_OVAL

    tpl, _ = template
    outer = R.outer_face(tpl, 20.0).numpy()
    face = np.zeros(tpl.n_vertices, bool)
    face[tpl.regions["face"]] = True
    assert outer.any() and not (outer & ~face).any()
    assert 0.03 < outer.sum() / face.sum() < 0.3, outer.sum()
    rest = R.dense_base(tpl, {}, {}).numpy()
    with torch.no_grad():
        lmk = tpl.lmk_model().landmarks[0].numpy()
    inner = np.setdiff1d(np.arange(478), FACE_OVAL)
    assert not outer[cKDTree(rest).query(lmk[inner])[1]].any()  # eyes, nose, mouth, cheeks stay out
    top = tpl.regions["face"][np.argmax(rest[tpl.regions["face"], 1])]
    assert outer[top]  # the forehead's top (where a hairline lies) is in
    assert R.outer_face(tpl, 30.0).numpy().sum() < outer.sum()


@pytest.mark.slow  # ~1-2 min on 2 cores: a remeshed scan and two registrations
def test_two_stage_registration_fits_hair(template, scan_set):
    from headforge.craft import register as R
    from headforge.craft.pipeline import ItemOptions, load_any

    tpl, _ = template
    scan, gt = load_any(scan_set / "id001", ItemOptions())
    cfg = replace(_fast(R.RegisterConfig.quick()), stage1_face_margin_mm=20.0)
    none = replace(cfg, stage1=replace(cfg.stage1, enabled=False), stage2=replace(cfg.stage2, enabled=False))
    base = R.register(tpl, scan, none)
    reg = R.register(tpl, scan, cfg)
    m0 = R.evaluate(tpl, base, base.vertices, scan, gt["labels"], gt["landmarks"])
    m = R.evaluate(tpl, reg, reg.vertices, scan, gt["labels"], gt["landmarks"])
    hair0, hair = m0["scan_to_reg"]["hair"]["median_mm"], m["scan_to_reg"]["hair"]["median_mm"]
    assert hair0 > 3.0, "the landmark fit alone cannot reach the hair"
    assert hair < 1.5 and hair < hair0 / 3, (hair0, hair)
    assert m["scan_to_reg"]["face"]["median_mm"] < 0.8
    assert m["max_edge_ratio"] < 4.0
    assert m["landmark_consistency_mm"] < 2.0
    # frozen parts did not move; displacements stay within the clip range
    frozen = np.union1d(tpl.regions["eyeballs"], tpl.regions["lower_neck"])
    assert reg.displacement[frozen].abs().max() < 1e-9
    # stage 1 moves the scalp, neck and the outer face (forehead, temples: hair lies there), not the inner face
    outer = R.outer_face(tpl, cfg.stage1_face_margin_mm).numpy()
    inner = np.setdiff1d(tpl.regions["face"], np.nonzero(outer)[0])
    moved1 = (reg.stage1 - reg.base).norm(dim=-1).numpy()
    assert moved1[inner].max() < 1e-9 and moved1[tpl.regions["ears"]].max() < 1e-9
    assert np.median(moved1[outer]) > 1e-5, np.median(moved1[outer])
    assert reg.displacement.abs().max() <= 20 / 120 + 1e-9


def test_bad_scans_give_one_line_errors(template, bald_set):
    from scipy.spatial.transform import Rotation

    from headforge.craft import register as R
    from headforge.craft.pipeline import ItemOptions, load_any
    from headforge.craft.scans import Scan

    tpl, _ = template
    cfg = _fast(R.RegisterConfig.quick())
    scan, _ = load_any(bald_set / "id000", ItemOptions())
    turned = Rotation.from_euler("y", 150, degrees=True).as_matrix()
    cases = [
        (Scan(scan.vertices @ turned.T, scan.faces, scan.landmarks @ turned.T, "turned", {"units": "m"}), "turned"),
        (Scan(scan.vertices * 10, scan.faces, scan.landmarks * 10, "big", {"units": "m"}), "wrong units"),
        (Scan(scan.vertices, scan.faces, None, "bare", {"units": "m"}), "no landmarks"),
        (Scan(scan.vertices, scan.faces, np.full((478, 3), np.nan), "nolmk", {"units": "m"}), "usable landmarks"),
        (Scan(scan.vertices * [1, 0, 1], scan.faces, scan.landmarks, "flat", {"units": "m"}), "degenerate"),
        (Scan(np.zeros((0, 3)), np.zeros((0, 3), int), None, "empty", {}), "empty"),
    ]
    for bad, message in cases:
        with pytest.raises(HeadforgeError) as info:
            R.register(tpl, bad, cfg)
        text = str(info.value)
        assert "\n" not in text and message in text, text


def test_register_command_fails_cleanly(tmp_path):
    from typer.testing import CliRunner

    from headforge.commands import craft

    runner = CliRunner()
    only_bad = tmp_path / "bad"
    only_bad.mkdir()
    (only_bad / "broken.obj").write_text("v 0 0 0\n")
    (only_bad / "notes.txt").write_text("not a scan")
    bad = runner.invoke(craft.app, ["register", str(only_bad), "-o", str(tmp_path / "m")])
    assert bad.exit_code == 1 and "no scan was registered" in bad.output
    assert "broken" in bad.output and "empty" in bad.output
    assert not (tmp_path / "m" / "broken").exists() and (tmp_path / "m" / "_failed" / "broken.json").exists()
    assert runner.invoke(craft.app, ["register", str(only_bad), "-o", str(tmp_path / "m"), "--preset", "slow"]).exit_code == 1
    assert runner.invoke(craft.app, ["register", str(only_bad), "-o", str(tmp_path / "m"), "--map-size", "100"]).exit_code == 1
    empty = tmp_path / "none"
    (empty / "id000.partial").mkdir(parents=True)  # a scan folder that `craft scans` was killed writing
    (empty / "id000.partial" / "scan.ply").write_text("ply\n")
    r = runner.invoke(craft.app, ["register", str(empty), "-o", str(tmp_path / "m3")])
    assert r.exit_code == 1 and "holds no scans" in r.output


@pytest.mark.slow  # ~1 min: one quick registration through the command
def test_register_command_isolates_and_resumes(tmp_path, bald_set):
    import shutil

    from typer.testing import CliRunner

    from headforge.commands import craft

    scans = tmp_path / "scans"
    shutil.copytree(bald_set / "id000", scans / "id000")
    (scans / "broken.obj").write_text("v 0 0 0\n")
    out = tmp_path / "maps"
    runner = CliRunner()
    result = runner.invoke(craft.app, ["register", str(scans), "-o", str(out), "--preset", "quick", "--map-size", "128",
                                       "--steps-scale", "0.25"])
    assert result.exit_code == 0, result.output
    assert "broken" in result.output and "failed" in result.output
    assert (out / "id000" / "map.png").exists() and (out / "id000" / "preview.png").exists()
    assert not (out / "broken").exists() and (out / "_failed" / "broken.json").exists()
    import json

    metrics = json.loads((out / "id000" / "metrics.json").read_text())
    assert metrics["roundtrip"]["median_mm"] < 0.2
    assert metrics["scan_to_reg"]["face"]["median_mm"] < 1.0
    again = runner.invoke(craft.app, ["register", str(scans), "-o", str(out), "--map-size", "128", "--steps-scale", "0.25"])
    assert "skipped" in again.output


@pytest.mark.slow
@pytest.mark.skipif(not (SCANS / "james.obj").exists(), reason="real scans not present")
def test_real_scan_james_registers(template):
    from headforge.craft import register as R
    from headforge.craft.pipeline import ItemOptions, load_any

    tpl, _ = template
    scan, _ = load_any(SCANS / "james.obj", ItemOptions())
    reg = R.register(tpl, scan, R.RegisterConfig.quick())
    m = R.evaluate(tpl, reg, reg.vertices, scan)
    assert m["scan_to_reg"]["all"]["median_mm"] < 2.0
