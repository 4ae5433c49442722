"""HeadCraft part 3: observations (depth maps, clouds), the landmark-free head fit, the partial
registration and its map, fitting StyleGAN2 / PCA to full and partial maps, ``craft fit``,
``craft depth``, ``craft transfer-hair`` and their bad-input errors. Tiny: a bald open-head
scan, 32 px runs, a few optimisation steps."""

import json

import numpy as np
import pytest
import torch
from test_craft_generative import TINY, cli, write_map_folder

from headforge.errors import HeadforgeError


@pytest.fixture(scope="module")
def tpl():
    from headforge.craft.pipeline import template_for

    return template_for("open-head", 1)


@pytest.fixture(scope="module")
def bald(tmp_path_factory):
    """A clean bald open-head scan (instant) and a frontal depth map of it (PNG + JSON)."""
    from headforge.craft import observe as O
    from headforge.craft.scans import ScanSetConfig, generate_scans, load_generated

    root = tmp_path_factory.mktemp("fitscan")
    generate_scans(root, ScanSetConfig(n=1, source="open-head", expression_every=9, sheet_px=64), log=lambda m: None)
    scan, _, gt = load_generated(root / "id000")
    target = gt["landmarks"].mean(0) + np.array([0, -0.02, -0.04])
    cam = O.depth_camera(target, 0.0, size=256)
    depth = O.render_depth(scan.vertices, scan.faces, cam)
    O.write_depth(root / "front.png", depth, cam)
    return root, scan, cam, depth


@pytest.fixture(scope="module")
def run(tmp_path_factory, tpl):
    root = tmp_path_factory.mktemp("fitrun")
    maps = write_map_folder(root / "maps", tpl, [f"id{i:03d}" for i in range(6)])
    out = root / "run"
    r = cli("craft", "train", maps, "-o", out, "--model", "stylegan2", "--steps", 3, "--holdout", 0.0, *TINY)
    assert r.exit_code == 0, r.output
    r = cli("craft", "train", maps, "-o", out, "--model", "pca", "--holdout", 0.0, *TINY)
    assert r.exit_code == 0, r.output
    return out


# ---------------------------------------------------------------- readers
def test_depth_png_round_trip_matches_the_surface(bald):
    """A written 16-bit depth map reads back to points on the scan (0.1 mm quantisation)."""
    from headforge.craft import observe as O
    from headforge.metrics.geometry import points_to_mesh

    root, scan, cam, depth = bald
    obs = O.read_depth(root / "front.png")
    assert obs.kind == "depth" and len(obs.points) == int((depth > 0).sum())
    world = (obs.points @ obs.to_source.T - cam.t) @ cam.R  # W -> camera -> scan
    d = points_to_mesh(world, scan.vertices, scan.faces)
    assert np.percentile(d, 99) < 2e-4
    assert obs.camera.R is not None and np.allclose(obs.camera.R, cam.R)


def test_depth_npy_and_scale(bald, tmp_path):
    from headforge.craft import observe as O

    root, _, cam, depth = bald
    np.save(tmp_path / "d.npy", depth * 1000)  # millimetres
    (tmp_path / "d.json").write_text(json.dumps({"K": cam.K.tolist()}))
    a = O.read_depth(tmp_path / "d.npy", depth_scale=0.001)
    b = O.read_depth(root / "front.png")
    assert len(a.points) == len(b.points)
    assert np.abs(np.sort(a.points[:, 2]) - np.sort(b.points[:, 2])).max() < 1e-4


def test_clouds_ply_and_pcd(bald, tmp_path):
    """PLY (vertices only), PCD unorganised and organised (NaN pixels dropped) read the same points."""
    import trimesh
    from pypcd4 import PointCloud

    from headforge.craft import observe as O

    root, _, _, _ = bald
    obs = O.read_depth(root / "front.png")
    cam_pts = obs.points @ obs.to_source.T  # the camera frame: a cloud's default axes
    trimesh.PointCloud(cam_pts).export(tmp_path / "c.ply")
    PointCloud.from_xyz_points(cam_pts.astype(np.float32)).save(str(tmp_path / "c.pcd"))
    H, W = obs.depth.shape
    grid = np.full((H * W, 3), np.nan, np.float32)
    rows, cols = np.nonzero(obs.depth > 0)
    grid[rows * W + cols] = cam_pts
    org = PointCloud.from_xyz_points(grid)
    org.metadata.width, org.metadata.height = W, H
    org.save(str(tmp_path / "org.pcd"))
    for name in ("c.ply", "c.pcd", "org.pcd"):
        c = O.read_observation(tmp_path / name)
        assert c.kind == "cloud" and len(c.points) == len(obs.points), name
        assert np.abs(np.sort(c.points[:, 2]) - np.sort(obs.points[:, 2])).max() < 1e-5, name


def test_bad_observations_are_one_line_errors(bald, tmp_path):
    import cv2
    import trimesh

    from headforge.craft import observe as O

    root, scan, cam, depth = bald
    cv2.imwrite(str(tmp_path / "nocam.png"), (depth / 1e-4).astype(np.uint16))
    with pytest.raises(HeadforgeError, match="no intrinsics"):
        O.read_depth(tmp_path / "nocam.png")
    cv2.imwrite(str(tmp_path / "zero.png"), np.zeros((64, 64), np.uint16))
    (tmp_path / "zero.json").write_text(json.dumps({"fx": 100, "fy": 100, "cx": 32, "cy": 32}))
    with pytest.raises(HeadforgeError, match="no valid depth"):
        O.read_depth(tmp_path / "zero.png")
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((64, 64, 3), np.uint8))
    (tmp_path / "rgb.json").write_text(json.dumps({"fx": 100, "fy": 100, "cx": 32, "cy": 32}))
    with pytest.raises(HeadforgeError, match="16-bit"):
        O.read_depth(tmp_path / "rgb.png")
    trimesh.PointCloud(np.random.default_rng(0).normal(0, 0.05, (O.MIN_POINTS - 1, 3))).export(tmp_path / "few.ply")
    with pytest.raises(HeadforgeError, match=f"at least {O.MIN_POINTS}"):
        O.read_observation(tmp_path / "few.ply")
    trimesh.Trimesh(scan.vertices, scan.faces).export(tmp_path / "mesh.ply")
    with pytest.raises(HeadforgeError, match="is a mesh"):
        O.read_cloud(tmp_path / "mesh.ply")
    (tmp_path / "broken.pcd").write_text("# .PCD v0.7\nFIELDS x y\nnonsense\n")
    with pytest.raises(HeadforgeError, match="broken.pcd"):
        O.read_observation(tmp_path / "broken.pcd")


# ---------------------------------------------------------------- head fit and partial registration
def test_head_fit_finds_a_turned_head_and_refuses_a_ball(bald, tpl, tmp_path):
    """The landmark-free fit finds the head in a 30-degree depth map -- its face, taken to the
    scan's frame, lies on the scan; its rotation is the scan's within a few degrees (translation
    and identity trade off, so the canonical frame itself is not compared) -- and finds no face
    in a sphere."""
    import trimesh

    from headforge.craft import observe as O
    from headforge.craft.partial import CloudFitConfig, fit_head_to_cloud
    from headforge.metrics.geometry import points_to_mesh

    root, scan, _, _ = bald
    template, _ = tpl
    cam = O.depth_camera(scan.vertices.mean(0), 30.0, size=160)
    O.write_depth(tmp_path / "side.png", O.render_depth(scan.vertices, scan.faces, cam), cam)
    obs = O.read_depth(tmp_path / "side.png")
    fit = fit_head_to_cloud(template, obs, CloudFitConfig(rigid_steps=40, steps=80, fit_points=4000))
    from headforge.craft import register as R

    base = R.dense_base(template, fit.alignment.params, {}).numpy()[template.regions["face"]]
    in_scan = (fit.alignment.to_scan(base) @ obs.to_source.T - cam.t) @ cam.R  # canonical -> W -> camera -> scan
    d = points_to_mesh(in_scan, scan.vertices, scan.faces)
    assert np.median(d) < 0.001 and np.percentile(d, 90) < 0.002, (np.median(d), np.percentile(d, 90))
    rot = cam.R.T @ obs.to_source @ fit.alignment.rotation.T
    assert np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))) < 6
    assert fit.face_coverage > 0.5
    ball = trimesh.creation.icosphere(4, radius=0.09).vertices
    trimesh.PointCloud(ball[ball[:, 2] > 0] * [1, -1, -1] + [0, 0, 0.6]).export(tmp_path / "ball.ply")
    with pytest.raises(HeadforgeError, match="no face found"):
        fit_head_to_cloud(template, O.read_observation(tmp_path / "ball.ply"), CloudFitConfig(rigid_steps=20, steps=20))


def test_partial_registration_and_map(bald, tpl):
    """Observed vertices lie on the scan after the partial registration; the map's mask covers
    the face island, not the back of the head."""
    from dataclasses import replace

    from headforge.craft import observe as O
    from headforge.craft.generative.data import texel_islands
    from headforge.craft.partial import CloudFitConfig, PartialConfig, density_of, partial_map, register_partial
    from headforge.metrics.geometry import points_to_mesh

    root, scan, cam, _ = bald
    template, duv = tpl
    cfg = PartialConfig.quick()
    cfg.register.stage1 = replace(cfg.register.stage1, steps=40)
    cfg.register.stage2 = replace(cfg.register.stage2, steps=20)
    cfg.fit = CloudFitConfig(rigid_steps=30, steps=60, fit_points=4000)
    obs = O.read_depth(root / "front.png")
    reg = register_partial(template, obs, cfg)
    assert reg.density == "dense" and 0.1 < reg.observed.mean() < 0.8
    assert reg.allowed[reg.observed].all()
    in_scan = (reg.fit.alignment.to_scan(reg.vertices.numpy()[reg.observed]) @ obs.to_source.T - cam.t) @ cam.R
    d = points_to_mesh(in_scan, scan.vertices, scan.faces)
    assert np.median(d) < 5e-4
    assert reg.threshold_mm == pytest.approx(max(3.0, 1.5e3 * obs.spacing_m()), rel=1e-6)  # quick: t from the spacing
    assert PartialConfig.paper().refine_spacing == 0 and PartialConfig.paper().refine_dense_units == 0.1  # the paper's t
    pm, mask = partial_map(reg, duv, 32)
    islands = texel_islands("open-head", 1, 32)
    assert mask.any() and (islands[mask] >= 0).all()
    assert (islands[mask] == 1).mean() > 0.5  # mostly the face island
    assert np.abs(pm[~mask]).max() == 0
    assert density_of(O.subsample(obs, 0.01), cfg) == "sparse"


# ---------------------------------------------------------------- latent fitting
def test_pca_fit_completes_a_map_in_its_span(tpl, tmp_path):
    """A map made of the PCA basis, observed on half the texels, is completed on the other half
    far better than by the mean map."""
    from headforge.craft.generative import invert as I
    from headforge.craft.generative.pca import PCAConfig, PCAModel

    rng = np.random.default_rng(0)
    model = PCAModel(PCAConfig(resolution=16, components=4))
    model.fit(torch.as_tensor(rng.normal(0, 1, (8, 3, 16, 16)), dtype=torch.float32))
    truth = model.decode(torch.tensor([[1.5, -1.0, 0.5, 0.8]]))
    mask = np.zeros((16, 16), bool)
    mask[:, :8] = True
    fitted, coeff = I.fit_pca(model, truth, mask, sigma_units=0.01)
    unseen = ~torch.as_tensor(mask)
    err = (fitted - truth)[..., unseen].abs().mean()
    err_mean = (model.mean.reshape(1, 3, 16, 16) - truth)[..., unseen].abs().mean()
    assert err < 0.05 * err_mean
    assert np.allclose(coeff.numpy(), [1.5, -1.0, 0.5, 0.8], atol=0.05)


def test_stylegan2_inversion_lowers_its_losses(run, tpl):
    """Full (W+ then noise) and partial (z, Delta-w, noise) fits lower their losses; the noise
    step changes only the scalp's noise; a map of another size is refused."""
    from dataclasses import replace

    from headforge.craft.generative import invert as I
    from headforge.craft.generative import train as T
    from headforge.craft.generative.data import face_texels

    trainer, meta = T.load_trained(run, "stylegan2")
    target = T.train_maps(run)[:1]
    cfg = replace(I.InvertConfig.quick(), full_steps=25, full_noise_steps=15, z_steps=25, dw_steps=15, noise_steps=15,
                  w_avg_samples=500)
    inv = I.invert_full(trainer, target, cfg)
    assert inv.history["w"][-1] < inv.history["w"][0]
    assert inv.history["noise"][-1] <= inv.history["noise"][0] + 1e-6
    face = face_texels("open-head", 1, 32)
    for name, noise in inv.noise.items():
        r = noise.shape[-1]
        if r == 32:
            assert noise[0, 0][torch.as_tensor(face)].abs().max() == 0, name
    mask = np.zeros((32, 32), bool)
    mask[:, 12:] = True
    part = I.invert_partial(trainer, target, mask, face, cfg)
    assert part.history["z"][-1] < part.history["z"][0]
    assert part.z is not None and part.ws.shape == inv.ws.shape
    assert inv.perceptual in ("lpips", "1-ssim")
    with pytest.raises(HeadforgeError, match="generator makes"):
        I.invert_full(trainer, torch.zeros(1, 3, 64, 64), cfg)


def test_partial_inversion_with_several_z_starts(run):
    """K z starts: "best" keeps the start with the lowest observed loss after the z step (the same
    start a one-start fit from that z would take), "mean" returns the mean of the K completions."""
    from dataclasses import replace

    from headforge.craft.generative import invert as I
    from headforge.craft.generative import train as T
    from headforge.craft.generative.data import face_texels

    trainer, _ = T.load_trained(run, "stylegan2")
    target = T.train_maps(run)[:1]
    face = face_texels("open-head", 1, 32)
    mask = np.zeros((32, 32), bool)
    mask[:, 12:] = True
    cfg = replace(I.InvertConfig.quick(), z_steps=10, dw_steps=5, noise_steps=5, w_avg_samples=100, z_starts=3)
    best = I.invert_partial(trainer, target, mask, face, cfg)
    losses = best.history["z_start_losses"]
    assert len(losses) == 3 and best.z.shape == (1, trainer.G_ema.cfg.z_dim)
    G = I._generator(trainer)
    M = torch.as_tensor(mask, dtype=torch.float32)[None, None]
    perc = I.Perceptual(cfg.patches)
    with torch.no_grad():
        kept = G.synthesis(G.ws(best.z))
        kept_loss = cfg.perceptual * perc(kept * M, target * M) + cfg.l1 * ((kept - target) * M).abs().mean()
    assert float(kept_loss) == pytest.approx(min(losses), rel=1e-4) and max(losses) > min(losses)
    mean = I.invert_partial(trainer, target, mask, face, replace(cfg, combine="mean"), noise=False)
    assert mean.ws.shape[0] == 3 and mean.map.shape == (1, 3, 32, 32)
    with torch.no_grad():
        each = G.synthesis(mean.ws)
    assert torch.allclose(mean.map, each.mean(0, keepdim=True), atol=1e-5)
    assert not torch.allclose(each[0], each[1], atol=1e-3)  # the starts differ: the mean is not one of them


def test_partial_inversion_truncation(run):
    """psi -> 0 maps every z to the average w, so the z step cannot move the map off the average
    map; psi = 1 (the paper) is the untruncated fit; psi outside (0, 1] is refused."""
    from dataclasses import replace

    from headforge.craft.generative import invert as I
    from headforge.craft.generative import train as T
    from headforge.craft.generative.data import face_texels

    trainer, _ = T.load_trained(run, "stylegan2")
    target = T.train_maps(run)[:1]
    face = face_texels("open-head", 1, 32)
    mask = np.zeros((32, 32), bool)
    mask[:, 12:] = True
    cfg = replace(I.InvertConfig.quick(), z_steps=10, dw_steps=0, noise_steps=0, w_avg_samples=100)
    G = I._generator(trainer)
    with torch.no_grad():
        average = G.synthesis(G.mapping.w_avg[None, None].repeat(1, G.num_ws, 1))
    tight = I.invert_partial(trainer, target, mask, face, replace(cfg, truncation=1e-6), noise=False)
    free = I.invert_partial(trainer, target, mask, face, cfg, noise=False)
    assert torch.allclose(tight.map, average, atol=1e-4)
    assert (free.map - average).abs().max() > 1e-2
    with pytest.raises(HeadforgeError, match="--truncation must be within"):
        replace(cfg, truncation=0.0)


# ---------------------------------------------------------------- the commands
def test_craft_depth_fit_and_transfer_hair(bald, run, tmp_path):
    """craft depth -> craft fit (StyleGAN2 and PCA, scored against the scan) -> transfer-hair."""
    root, scan, _, _ = bald
    depth = tmp_path / "d.png"
    r = cli("craft", "depth", root / "id000", "-o", depth, "--yaw", 20, "--size", 192)
    assert r.exit_code == 0, r.output
    assert depth.is_file() and depth.with_suffix(".json").is_file()
    outs = {}
    for method in ("stylegan2", "pca"):
        out = tmp_path / f"fit_{method}"
        r = cli("craft", "fit", depth, "--model", run, "-o", out, "--method", method, "--steps-scale", 0.03,
                "--gt", root / "id000")
        assert r.exit_code == 0, r.output
        for name in ("completed.ply", "completed_canonical.ply", "map.png", "partial_map.png", "partial_map_mask.png",
                     "latent.safetensors", "params.json", "metrics.json", "picture.png"):
            assert (out / name).is_file(), (method, name)
        m = json.loads((out / "metrics.json").read_text())
        g = m["ground_truth"]
        assert {"all", "observed", "unseen", "unseen_back_hair"} <= set(g)
        assert g["observed"]["gt_to_pred_mm"] < g["unseen"]["gt_to_pred_mm"] + 5  # sane, finite
        assert 0 < g["observed"]["share"] < 1
        assert not (tmp_path / f"fit_{method}.partial").exists()
        outs[method] = out
    # the completed mesh in the observation's frame lies on the depth points (camera frame)
    import trimesh

    from headforge.craft import observe as O
    from headforge.metrics.geometry import points_to_mesh

    obs = O.read_depth(depth)
    mesh = trimesh.load(outs["pca"] / "completed.ply", process=False)
    d = points_to_mesh(obs.points @ obs.to_source.T, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    assert np.median(d) < 0.005  # a few registration steps only: the frames are what is checked here
    canon = trimesh.load(outs["pca"] / "completed_canonical.ply", process=False)
    a = json.loads((outs["pca"] / "params.json").read_text())["alignment"]
    again = (np.asarray(canon.vertices) @ np.asarray(a["rotation"]) + a["translation"]) @ np.asarray(a["observation_to_file_axes"]).T
    assert np.abs(again - np.asarray(mesh.vertices)).max() < 1e-5
    r = cli("craft", "transfer-hair", outs["stylegan2"], outs["pca"], "-o", tmp_path / "hair")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "hair" / "sheet.png").is_file() and (tmp_path / "hair" / "mesh.ply").is_file()


def test_craft_fit_bad_inputs(bald, run, tmp_path):
    import cv2

    root, _, _, depth = bald
    cv2.imwrite(str(tmp_path / "nocam.png"), (depth / 1e-4).astype(np.uint16))
    r = cli("craft", "fit", tmp_path / "nocam.png", "--model", run, "-o", tmp_path / "o1")
    assert r.exit_code == 1 and "no intrinsics" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o1.partial").exists()
    r = cli("craft", "fit", root / "front.png", "--model", tmp_path, "-o", tmp_path / "o2")
    assert r.exit_code == 1 and "not a headcraft run folder" in r.output
    r = cli("craft", "fit", root / "front.png", "--model", run, "-o", tmp_path / "o3", "--method", "vae")
    assert r.exit_code == 1 and "unknown --method 'vae'" in r.output
    r = cli("craft", "fit", root / "front.png", "--model", run, "-o", tmp_path / "o6", "--z-starts", 0)
    assert r.exit_code == 1 and "--z-starts must be 1 to 64" in r.output and not (tmp_path / "o6").exists()
    r = cli("craft", "fit", root / "front.png", "--model", run, "-o", tmp_path / "o7", "--truncation", 1.5)
    assert r.exit_code == 1 and "--truncation must be within (0, 1]" in r.output and not (tmp_path / "o7").exists()
    # a generator checkpoint of another resolution
    import shutil

    other = tmp_path / "other"
    shutil.copytree(run, other)
    meta = json.loads((other / "stylegan2" / "checkpoint.json").read_text())
    meta["resolution"] = 64
    (other / "stylegan2" / "checkpoint.json").write_text(json.dumps(meta))
    r = cli("craft", "fit", root / "front.png", "--model", other, "-o", tmp_path / "o4")
    assert r.exit_code == 1 and "trained at 64 px" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "o4").exists()
    run_meta = json.loads((other / "run.json").read_text())
    del run_meta["methods"]["pca"]
    (other / "run.json").write_text(json.dumps(run_meta))
    r = cli("craft", "fit", root / "front.png", "--model", other, "-o", tmp_path / "o5", "--method", "pca")
    assert r.exit_code == 1 and "has no trained pca" in r.output
