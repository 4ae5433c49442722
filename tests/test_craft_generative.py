"""HeadCraft part 2: training set, generative models, sampling, seam post-processing, TBN
transfer, evaluation, and the CLI's bad-input errors. Tiny: 32 px maps, a handful of steps."""

import json
import shutil

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from headforge.errors import HeadforgeError

SIZE = 32
TINY = ["--set", "resolution=32", "--set", "channel_base=128", "--set", "channel_max=16", "--set", "z_dim=16",
        "--set", "w_dim=16", "--set", "widths=8,8,8", "--set", "strides=1,2,2", "--set", "latent=8",
        "--set", "codebook=16", "--set", "prior_channels=8", "--set", "prior_layers=1", "--set", "components=4",
        "--set", "batch=4"]


@pytest.fixture(scope="module")
def tpl():
    from headforge.craft.pipeline import template_for

    return template_for("open-head", 1)


def _field(x, rng):
    a = rng.uniform(0.002, 0.012, 3)
    f = rng.uniform(10, 40, 3)
    hair = np.clip(x[:, 1] - 0.02, 0, None) * rng.uniform(0.1, 0.6)
    return np.stack([a[0] * np.sin(f[0] * x[:, 1]), a[1] * np.cos(f[1] * x[:, 0]), a[2] * np.sin(f[2] * x[:, 2]) + hair], 1)


def write_map_folder(folder, tpl, keys, seed=0):
    """Registered-style item folders (map.png, params.json, registered.ply) of smooth fields."""
    from headforge.craft import register as R
    from headforge.craft import uvmap
    from headforge.craft.scans import write_ply

    template, duv = tpl
    base = R.dense_base(template, {}, R.RegisterConfig().smooth_iterations).numpy()
    for i, key in enumerate(keys):
        rng = np.random.default_rng([seed, i])
        raw, mask = uvmap.bake(_field(base, rng), duv, SIZE)
        m = uvmap.postprocess_seams(raw, mask, duv, blend=0)
        d = folder / key
        d.mkdir(parents=True)
        uvmap.write_map(d / "map.png", m, mask)
        shape = np.zeros((1, template.model.n_shape), np.float32)
        shape[0, :5] = rng.normal(0, 0.5, 5)
        params = {"shape": shape.tolist(), "expression": np.zeros((1, template.model.n_expr)).tolist(),
                  "jaw_pose": np.zeros((1, 3)).tolist()}
        (d / "params.json").write_text(json.dumps({"head_model": "open-head", "levels": 1, "params": params}))
        v = uvmap.apply_map(template, m, duv, {"shape": torch.as_tensor(shape)}).numpy()
        write_ply(d / "registered.ply", v, template.faces.numpy())
    return folder


@pytest.fixture(scope="module")
def maps(tmp_path_factory, tpl):
    root = tmp_path_factory.mktemp("craftgen")
    train = write_map_folder(root / "maps", tpl, ["id000", "id001", "id001_expr", "id002", "id003", "id004"])
    held = write_map_folder(root / "held", tpl, ["id100", "id101", "id101_expr"], seed=1)
    return root, train, held


def cli(*args):
    from headforge.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def run(maps):
    root, train, _ = maps
    out = root / "run"
    r = cli("craft", "train", train, "-o", out, "--model", "all", "--steps", 3, "--holdout", 0.2, *TINY)
    assert r.exit_code == 0, r.output
    return out


def test_training_set_face_replacement_and_split(maps):
    from headforge.craft.generative import data as D

    _, train, _ = maps
    ms = D.load_maps(train)
    assert ms.face_replaced == ["id001_expr"]
    face = D.face_texels("open-head", 1, SIZE)
    a, b = ms.maps[ms.keys.index("id001_expr")], ms.maps[ms.keys.index("id001")]
    assert np.array_equal(a[face], b[face])
    scalp = D.texel_islands("open-head", 1, SIZE) == 0
    assert not np.allclose(a[scalp], b[scalp]), "the scalp keeps the expression scan's own map"
    tr, held = D.split_by_identity(ms.items, 0.4, 0)
    ids_tr = {ms.items[i].identity for i in tr}
    ids_held = {ms.items[i].identity for i in held}
    assert ids_tr and ids_held and not ids_tr & ids_held
    assert sorted(tr + held) == list(range(len(ms.items)))


def test_train_all_resume_sample_interpolate_eval(run, maps, tmp_path):
    root, train, held = maps
    meta = json.loads((run / "run.json").read_text())
    assert set(meta["methods"]) == {"stylegan2", "pca", "vae", "vqvae"}
    assert not set(meta["train_keys"]) & set(meta["heldout_keys"])
    for m in meta["methods"]:
        assert (run / m / "samples.png").is_file() and (run / m / "checkpoint.safetensors").is_file()
    # resume: finished runs are not retrained; more steps continue from the checkpoint
    r = cli("craft", "train", train, "-o", run, "--model", "vae", "--steps", 3, "--holdout", 0.2, *TINY)
    assert r.exit_code == 0 and "already trained" in r.output, r.output
    r = cli("craft", "train", train, "-o", run, "--model", "vae", "--steps", 5, "--holdout", 0.2, *TINY)
    assert r.exit_code == 0 and "resuming at step 3" in r.output, r.output
    assert json.loads((run / "run.json").read_text())["methods"]["vae"]["steps"] == 5
    # sample: maps, meshes, sheet
    r = cli("craft", "sample", run, "-n", 1, "-o", tmp_path / "s", "--truncation", 0.7, "--seed", 3)
    assert r.exit_code == 0, r.output
    assert (tmp_path / "s" / "sheet.png").is_file()
    from headforge.craft import uvmap

    m = uvmap.read_map(tmp_path / "s" / "sample_000" / "map.png", SIZE)
    assert np.isfinite(m).all()
    # eval of one model against separate held-out scans, and against the training folder itself
    # (then only the identities the run held out are scored)
    r = cli("craft", "eval", run, held, "--points", 128, "--seeds", 1, "--model", "pca", "-o", tmp_path / "e1.json")
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "e1.json").read_text())
    row = res["rows"]["pca"]
    assert row["mmd"] > 0 and 0 <= row["cov"] <= 100 and 0 <= row["one_nna"] <= 100 and row["jsd"] >= 0
    assert res["n_heldout"] == 3 and res["n_neutral"] == 2 and row["memo_sample_nn_mm"] > 0
    r = cli("craft", "eval", run, train, "--points", 128, "--seeds", 1, "--model", "pca", "-o", tmp_path / "e2.json")
    assert r.exit_code == 0, r.output
    held_keys = json.loads((run / "run.json").read_text())["heldout_keys"]
    assert json.loads((tmp_path / "e2.json").read_text())["n_heldout"] == len(held_keys) > 0


@pytest.mark.slow
def test_eval_every_model_and_interpolate(run, maps, tmp_path):
    _, _, held = maps
    r = cli("craft", "interpolate", run, "-o", tmp_path / "i", "--steps", 3, "--model", "stylegan2")
    assert r.exit_code == 0 and (tmp_path / "i" / "strip.png").is_file(), r.output
    r = cli("craft", "eval", run, held, "--points", 256, "--seeds", 2, "-o", tmp_path / "eval.json")
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "eval.json").read_text())
    assert set(res["rows"]) == {"stylegan2", "pca", "vae", "vqvae", "bare"}
    for row in res["rows"].values():
        assert row["mmd"] > 0 and 0 <= row["cov"] <= 100 and 0 <= row["one_nna"] <= 100 and row["jsd"] >= 0


def test_truncation_zero_gives_the_mean_map(run):
    from headforge.craft.generative import sample as S
    from headforge.craft.generative import train as T

    pca = S.load(run, "pca")
    a = S.sample_maps(pca, 2, 0.0, seed=0)
    mean = T.train_maps(run).double().mean(0).permute(1, 2, 0).numpy() * 0.02
    assert np.allclose(a[0], mean, atol=1e-6) and np.allclose(a[1], mean, atol=1e-6)
    assert not np.allclose(S.sample_maps(pca, 1, 1.0, seed=0)[0], mean, atol=1e-6)
    sg = S.load(run, "stylegan2")
    x, y = S.sample_maps(sg, 1, 0.0, seed=0), S.sample_maps(sg, 1, 0.0, seed=5)
    assert np.allclose(x, y)
    G = sg.trainer.G_ema
    ws = G.mapping.w_avg[None, None].repeat(1, G.num_ws, 1)
    assert np.allclose(x[0], G.synthesis(ws)[0].permute(1, 2, 0).double().numpy() * 0.02, atol=1e-6)
    vae = S.load(run, "vae")
    assert np.allclose(S.sample_maps(vae, 1, 0.0, seed=0), S.sample_maps(vae, 1, 0.0, seed=9))


def test_vqvae_decodes_its_own_codes_as_its_forward_pass():
    """The VQ-VAE's samples decode PixelCNN codes: decoding a map's own codes must give the same
    map as the forward pass (the quantiser's index lookup is channel-first for image feature
    maps; read as (B, h*w, dim) it scrambled every sample)."""
    from headforge.craft.generative.vqvae import VQVAE, VQVAEConfig

    torch.manual_seed(0)
    model = VQVAE(VQVAEConfig(resolution=32, widths=[8, 8, 8], strides=[1, 2, 2], codebook=16))
    x = torch.randn(4, 3, 32, 32) * 0.3
    model.train()
    model(x)  # k-means initialises the codebook
    model.eval()
    with torch.no_grad():
        rec, idx, _ = model(x)
    assert idx.shape == (4, 8, 8)
    torch.testing.assert_close(model.decode_codes(idx), rec)


def test_stylegan2_noise_off_on_the_face():
    from headforge.craft.generative.stylegan2 import Generator, StyleGAN2Config

    face = np.zeros((32, 32), bool)
    face[:, 16:] = True
    G = Generator(StyleGAN2Config(resolution=32, channel_base=64, channel_max=8, z_dim=8, w_dim=8), face)
    for block in G.layers:
        for layer in block:
            r = layer.noise.shape[-1]
            assert (layer.noise[..., r // 2:] == 0).all() and (layer.noise[..., : r // 2] != 0).any()
    assert G(torch.randn(2, 8)).shape == (2, 3, 32, 32)


def test_seam_postprocess_leaves_no_reachable_empty_texel(tpl):
    from headforge.craft import uvmap
    from headforge.craft.generative import sample as S

    template, duv = tpl
    rng = np.random.default_rng(0)
    gen = rng.normal(0, 0.003, (SIZE, SIZE, 3))
    covered = uvmap.texel_islands(duv, SIZE) >= 0
    gen[~covered] = np.nan  # a generator writes anything where no triangle is; NaN makes it visible
    before = uvmap.lookup(gen, duv, template.n_vertices).numpy()
    assert np.isnan(before).any(), "bilinear lookups do reach empty texels at this size"
    out = S.postprocess(gen[None], {"head_model": "open-head", "levels": 1})[0]
    assert np.isfinite(out).all()
    after = uvmap.lookup(out, duv, template.n_vertices).numpy()
    assert np.isfinite(after).all()
    pairs, _ = uvmap.seam_pairs(duv, SIZE)
    a, b = out[pairs[:, 0, 0], pairs[:, 0, 1]], out[pairs[:, 1, 0], pairs[:, 1, 1]]
    assert np.abs(a - b).max() < 1e-12, "the two sides of the seam agree"


def test_tbn_transfer_reproduces_the_posed_mesh(tpl):
    """A displaced neutral head turned by the head pose, and with the jaw opened: the TBN
    transfer puts each displacement where the rigidly moving surface carries it."""
    import roma

    from headforge.craft import register as R
    from headforge.craft.animate import Animator

    template, duv = tpl
    base = R.dense_base(template, {}, R.RegisterConfig().smooth_iterations)
    disp = torch.as_tensor(_field(base.numpy(), np.random.default_rng(3)))
    raw, mask = __import__("headforge.craft.uvmap", fromlist=["bake"]).bake(disp, duv, 128)
    from headforge.craft import uvmap

    m = uvmap.postprocess_seams(raw, mask, duv, blend=0)
    anim = Animator(template, duv, m, None)
    d = anim.displacement
    # rigid head pose: the registered posed mesh is the rotated neutral one
    rot = torch.tensor([[0.3, -0.5, 0.2]])
    posed = anim.posed_mesh({"root_pose": rot})
    posed_base = R.dense_base(template, {"root_pose": rot}, R.RegisterConfig().smooth_iterations)
    Rm = roma.rotvec_to_rotmat(rot[0].double())
    want = posed_base + d @ Rm.T
    err = (posed - want).norm(dim=-1)
    assert err.max() < 1e-6, float(err.max())
    naive = (posed_base + d - want).norm(dim=-1)
    assert naive.median() > 1e-3, "adding the displacements unrotated would be wrong"
    # jaw: vertices skinned wholly to the jaw move rigidly; their displacements turn with it
    jaw = torch.tensor([[0.25, 0.0, 0.0]])
    posed = anim.posed_mesh({"jaw_pose": jaw})
    jb = R.dense_base(template, {"jaw_pose": jaw}, R.RegisterConfig().smooth_iterations)
    data = template.data
    names = list(getattr(data, "joint_names", [])) or None
    j = names.index("jaw") if names and "jaw" in names else 2
    w = torch.as_tensor(data.weights[:, j])
    dense_w = template.subdivision.apply(w[:, None].double())[:, 0]
    rigid = torch.nonzero(dense_w > 0.999)[:, 0]
    if len(rigid) > 50:
        Rj = roma.rotvec_to_rotmat(jaw[0].double())
        got = (posed - jb)[rigid]
        # far from the jaw's skinning border the frames turn with the jaw (interior vertices)
        cos = torch.nn.functional.cosine_similarity(got, d[rigid] @ Rj.T, dim=-1)
        big = d[rigid].norm(dim=-1) > 1e-3
        assert cos[big].median() > 0.999


def test_bad_input_one_line_errors(maps, run, tmp_path, tpl):
    import cv2

    root, train, _ = maps
    # empty folder
    (tmp_path / "empty").mkdir()
    r = cli("craft", "train", tmp_path / "empty", "-o", tmp_path / "r0", *TINY)
    assert r.exit_code == 1 and "holds no displacement maps" in r.output
    # mixed sizes
    mixed = tmp_path / "mixed"
    shutil.copytree(train, mixed)
    img = cv2.imread(str(mixed / "id003" / "map.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(mixed / "id003" / "map.png"), cv2.resize(img, (64, 64)))
    r = cli("craft", "train", mixed, "-o", tmp_path / "r1", *TINY)
    assert r.exit_code == 1 and "differ in size or dtype" in r.output, r.output
    # mixed dtypes
    cv2.imwrite(str(mixed / "id003" / "map.png"), (img // 256).astype(np.uint8))
    r = cli("craft", "train", mixed, "-o", tmp_path / "r1", *TINY)
    assert r.exit_code == 1 and "differ in size or dtype" in r.output, r.output
    # a run of another resolution
    r = cli("craft", "train", train, "-o", run, "--model", "pca", "--holdout", 0.2)
    assert r.exit_code == 1 and "px" in r.output and len(r.output.strip().splitlines()) == 1, r.output
    # a checkpoint of another method / resolution
    other = tmp_path / "run2"
    shutil.copytree(run, other)
    shutil.rmtree(other / "stylegan2")
    shutil.copytree(run / "vae", other / "stylegan2")
    r = cli("craft", "sample", other, "-n", 1, "-o", tmp_path / "x")
    assert r.exit_code == 1 and "is a vae checkpoint, not stylegan2" in r.output, r.output
    ck = json.loads((run / "pca" / "checkpoint.json").read_text())
    ck["resolution"] = 64
    (other / "pca" / "checkpoint.json").write_text(json.dumps(ck))
    r = cli("craft", "sample", other, "-n", 1, "--model", "pca", "-o", tmp_path / "x")
    assert r.exit_code == 1 and "trained at 64 px" in r.output, r.output
    # a model not trained here
    r = cli("craft", "sample", tmp_path / "r0", "-n", 1)
    assert r.exit_code == 1 and "not a headcraft run folder" in r.output
    # a driving dataset tracked with another head model
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "dataset.json").write_text(json.dumps({"format": "headforge-dataset", "version": 1, "model": "flame",
                                                 "resolution": 64, "intrinsics": [], "frames": []}))
    r = cli("craft", "animate", train / "id000" / "map.png", "--driving", ds, "-o", tmp_path / "a.mp4")
    assert r.exit_code == 1 and "tracked with 'flame'" in r.output, r.output


def test_animate_cli_writes_video(maps, tmp_path):
    from safetensors.torch import save_file

    root, train, _ = maps
    ds = tmp_path / "ds"
    ds.mkdir()
    T = 2
    frames = [{"index": i, "valid": True, "split": "train"} for i in range(T)]
    (ds / "dataset.json").write_text(json.dumps({"format": "headforge-dataset", "version": 1, "model": "open-head",
                                                 "resolution": 64, "intrinsics": [], "frames": frames, "fps": 10}))
    tr = {"shape": torch.zeros(1, 100), "expression": torch.rand(T, 52) * 0.5, "translation": torch.zeros(T, 3),
          "landmarks": torch.zeros(T, 478, 2), "valid": torch.ones(T, dtype=torch.bool)}
    for k in ("root_pose", "neck_pose", "jaw_pose", "eye_left_pose", "eye_right_pose"):
        tr[k] = torch.zeros(T, 3)
    tr["jaw_pose"][:, 0] = torch.linspace(0, 0.3, T)
    save_file(tr, str(ds / "tracking.safetensors"))
    r = cli("craft", "animate", train / "id000" / "map.png", "--driving", ds, "-o", tmp_path / "a.mp4", "--size", 48)
    assert r.exit_code == 0, r.output
    assert (tmp_path / "a.mp4").stat().st_size > 1000
