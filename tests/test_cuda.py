"""CUDA paths against the CPU: the vectorised rasterizer and point splatting, NHA's energies and
gradients, and a training run that checkpoints on the GPU and resumes on the CPU. Skipped
without a CUDA GPU (CI has none; run them where one is: ``pytest tests/test_cuda.py``).

``HEADFORGE_TEST_DATASET`` may name a tracked dataset to use instead of making the synthetic
one (which needs MediaPipe)."""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")


@pytest.fixture(scope="module")
def dataset(request) -> Path:
    given = os.environ.get("HEADFORGE_TEST_DATASET")
    if given:
        return Path(given)
    return request.getfixturevalue("synth_bench")[0] / "subject_00"


@pytest.fixture(scope="module")
def tiny_config():
    from headforge.avatars.nha.config import NHAConfig

    config = NHAConfig.quick()
    config.resolution = 128
    config.geometry_iters, config.texture_iters, config.joint_iters = 4, 2, 2
    config.checkpoint_every, config.val_every, config.val_frames, config.tto_steps, config.align_steps = 2, 4, 2, 2, 2
    config.val_tto_steps = 2
    return config


def test_rasterizer_on_cuda_equals_the_numba_kernel(open_head):
    from headforge.render import mesh
    from headforge.render.camera import Cameras, look_at_head

    verts = open_head(shape=torch.zeros(2, open_head.n_shape)).vertices.double()
    cams = Cameras.from_pinhole([look_at_head(256, 256, distance=0.5, yaw_deg=y) for y in (0, 40)], torch.float64)
    cpu = mesh.rasterize(cams, verts, open_head.faces)
    gpu = mesh.rasterize(cams.to("cuda"), verts.cuda(), open_head.faces.cuda())
    assert gpu.face_id.is_cuda
    same = (gpu.face_id.cpu() == cpu.face_id).double().mean().item()
    assert same > 0.9999, same
    both = (gpu.face_id.cpu() == cpu.face_id) & cpu.mask
    np.testing.assert_allclose(gpu.bary.cpu()[both].numpy(), cpu.bary[both].numpy(), atol=1e-9)
    np.testing.assert_allclose(gpu.depth.cpu()[both].numpy(), cpu.depth[both].numpy(), atol=1e-9)


def test_splatting_on_cuda_equals_the_numba_kernel():
    import trimesh

    from headforge.render import kernels, points
    from headforge.render.camera import Cameras, look_at_head

    pos, _ = trimesh.sample.sample_surface(trimesh.creation.icosphere(4, radius=0.1), 20000, seed=0)
    pts = torch.tensor(pos)[None].expand(2, -1, -1).clone()
    pts[1, :100] = float("nan")
    gen = torch.Generator().manual_seed(0)
    radius = 0.8 + 1.5 * torch.rand(2, pts.shape[1], generator=gen, dtype=torch.float64)
    feats = torch.rand(2, pts.shape[1], 3, generator=gen, dtype=torch.float64)
    cams = Cameras.from_pinhole([look_at_head(256, 192, distance=0.5, yaw_deg=y) for y in (0, 40)], torch.float64)
    # the kernel alone on identical screen-space inputs: bit for bit (the same float64 arithmetic)
    xyz, H, W = cams.project_finite(pts), cams.height, cams.width
    idx, depth = kernels.splat_numba(xyz.numpy(), radius.numpy(), H, W, 8)
    gpu_idx, gpu_depth = kernels.splat_torch(xyz.cuda(), radius.cuda(), H, W, 8, chunk_pairs=1 << 16)
    assert gpu_idx.is_cuda and gpu_depth.is_cuda
    np.testing.assert_array_equal(gpu_idx.cpu().numpy(), idx)
    np.testing.assert_array_equal(gpu_depth.cpu().numpy(), depth)
    # the whole splat: CUDA tensors take the torch path; projections may differ in the last bits
    cpu = points.splat(cams, pts, feats, radius, K=8)
    gpu = points.splat(cams.to("cuda"), pts.cuda(), feats.cuda(), radius.cuda(), K=8)
    assert gpu.features.is_cuda and gpu.fragments.idx.is_cuda
    agree = (gpu.fragments.idx.cpu() == cpu.fragments.idx).all(-1)
    assert agree.double().mean().item() > 0.9999 and cpu.mask.gt(0.5).double().mean() > 0.1
    np.testing.assert_allclose(gpu.features.cpu()[agree].numpy(), cpu.features[agree].numpy(), atol=1e-9)
    np.testing.assert_allclose(gpu.mask.cpu()[agree].numpy(), cpu.mask[agree].numpy(), atol=1e-9)
    off = (gpu.max_weight.cpu() - cpu.max_weight).abs() > 1e-6
    assert off.double().mean().item() < 1e-3

def test_nha_energies_and_gradients_on_cuda_match_the_cpu(dataset, tiny_config):
    from headforge.avatars.frames import FrameData
    from headforge.avatars.nha.method import build_avatar, losses
    from headforge.avatars.run import RunAssets
    from headforge.metrics.protocol import TrackedHead

    torch.manual_seed(0)
    assets = RunAssets.from_dataset(dataset)
    avatar = build_avatar(assets, tiny_config)
    data = FrameData(dataset, "train", tiny_config.resolution, TrackedHead(assets.head_data(), assets.tracking["shape"]))
    on_gpu = copy.deepcopy(avatar).cuda()
    data_gpu = copy.deepcopy(data).to("cuda")
    rows = torch.tensor([0, 1])
    cpu_terms = losses(avatar, data.batch(rows), data.K, tiny_config, "joint")
    gpu_terms = losses(on_gpu, data_gpu.batch(rows), data_gpu.K, tiny_config, "joint")
    assert cpu_terms.keys() == gpu_terms.keys()
    for k in cpu_terms:
        assert gpu_terms[k].is_cuda
        assert torch.allclose(gpu_terms[k].cpu(), cpu_terms[k], rtol=2e-3, atol=1e-6), (k, cpu_terms[k], gpu_terms[k])
    sum(cpu_terms.values()).backward()
    sum(gpu_terms.values()).backward()
    for (name, p), q in zip(avatar.named_parameters(), on_gpu.parameters()):
        if p.grad is None:
            assert q.grad is None or q.grad.abs().max() == 0, name
            continue
        err = (q.grad.cpu() - p.grad).norm() / p.grad.norm().clamp(min=1e-12)
        assert err < 2e-2, (name, float(err))


def kill_on_gpu_resume_on_cpu(method: str, dataset: Path, run: Path, config, interrupt_after):
    """Kill a ``method`` fit on the GPU after 4 iterations and finish it on the CPU; returns the
    interrupted run's state.json, the finished run loaded onto the GPU, its held-out frames (on
    the CPU) and their score on the GPU."""
    from headforge.avatars.engine import fit, score
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.metrics.protocol import TrackedHead

    with pytest.raises(KeyboardInterrupt):
        fit(method, dataset, run, config, log=lambda m: None, progress=interrupt_after(5), device="cuda")
    state = json.loads((run / "state.json").read_text())
    assert state["iteration"] == 4
    metrics = fit(method, dataset, run, config, log=lambda m: None, device="cpu")
    assert metrics["device"] == "cpu" and 5 < metrics["val_psnr"] < 60
    r = load_run(run, "cuda")
    assert next(r.avatar.parameters()).is_cuda
    val = FrameData(dataset, "val", r.config.resolution, TrackedHead(r.assets.head_data(), r.assets.tracking["shape"]))
    on_gpu = score(r.method, r.avatar, copy.deepcopy(val).to("cuda"), r.config)[0]
    return state, r, val, on_gpu


def test_fit_on_cuda_checkpoints_and_resumes_on_the_cpu(dataset, tiny_config, tmp_path, interrupt_after):
    from headforge.avatars.engine import score

    state, r, val, on_gpu = kill_on_gpu_resume_on_cpu("nha", dataset, tmp_path / "run", tiny_config, interrupt_after)
    assert state["aligned"] > 0
    on_cpu = score(r.method, r.avatar.cpu(), val, r.config)[0]
    assert abs(on_gpu["psnr"] - on_cpu["psnr"]) < 0.05, (on_gpu, on_cpu)


@pytest.fixture(scope="module")
def point_config():
    """A small PointAvatar (float64 in the energy test) with the quick preset's terms on."""
    from headforge.avatars.pointavatar.config import PointAvatarConfig

    return PointAvatarConfig(resolution=128, iterations=8, init_points=1500, max_points=3000, init_cloud="head",
                             upsample_every=3, prune_every=2, canonical_width=64, canonical_layers=4,
                             canonical_skip=2, frequencies=4, deformer_width=64, deformer_layers=3, shading_width=32,
                             eikonal_samples=500, val_every=8, checkpoint_every=2, val_frames=2, tto_steps=2,
                             tto_photometric_steps=0, val_tto_steps=1, points_per_pixel=6, w_landmarks=1.0,
                             w_eyelids=1.0)


def test_pointavatar_energies_and_gradients_on_cuda_match_the_cpu(dataset, point_config):
    """The same float64 avatar and batch on both devices: every energy and every parameter's
    gradient agree (splatting visibility may differ on a few boundary pixels, hence not bit for bit)."""
    from headforge.avatars import registry
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import RunAssets
    from headforge.metrics.protocol import TrackedHead

    torch.manual_seed(0)
    method = registry.get("pointavatar")
    assets = RunAssets.from_dataset(dataset)
    avatar = method.build(assets, point_config).double()
    data = FrameData(dataset, "train", point_config.resolution, TrackedHead(assets.head_data(), assets.tracking["shape"]))
    on_gpu = copy.deepcopy(avatar).cuda()
    data_gpu = copy.deepcopy(data).to("cuda")
    batch, batch_gpu = data.batch(torch.tensor([0, 1])), data_gpu.batch(torch.tensor([0, 1]))
    batch = {k: v.double() if torch.is_floating_point(v) else v for k, v in batch.items()}
    batch_gpu = {k: v.double() if torch.is_floating_point(v) else v for k, v in batch_gpu.items()}
    for stage in ("train", "align"):
        cpu_terms = method.losses(avatar, batch, data.K.double(), point_config, stage)
        gpu_terms = method.losses(on_gpu, batch_gpu, data_gpu.K.double(), point_config, stage)
        assert cpu_terms.keys() == gpu_terms.keys() and "rgb" in cpu_terms
        assert ("landmarks" in cpu_terms) == (stage == "align")  # the fitting's terms
        for k in cpu_terms:
            assert gpu_terms[k].is_cuda
            assert torch.allclose(gpu_terms[k].cpu(), cpu_terms[k], rtol=1e-3, atol=1e-7), (stage, k, cpu_terms[k], gpu_terms[k])
    avatar.zero_grad()
    on_gpu.zero_grad()
    sum(cpu_terms.values()).backward()
    sum(gpu_terms.values()).backward()
    compared = 0
    for (name, p), q in zip(avatar.named_parameters(), on_gpu.parameters()):
        if p.grad is None or p.grad.abs().max() == 0:
            assert q.grad is None or q.grad.abs().max() < 1e-9, name
            continue
        err = (q.grad.cpu() - p.grad).norm() / p.grad.norm()
        assert err < 1e-2, (name, float(err))
        compared += 1
    assert compared > 0


def test_pointavatar_fits_on_cuda_and_resumes_on_the_cpu(dataset, point_config, tmp_path, interrupt_after):
    """A PointAvatar run trains and scores on the GPU end to end (novel views included); one killed
    on the GPU (after a prune and a doubling) resumes on the CPU; the finished avatar scores the same
    held-out PSNR on either device and moves between them (its cached canonical state follows), relit
    renders too."""
    from headforge.avatars.engine import fit, score
    from headforge.render.camera import Cameras

    whole = fit("pointavatar", dataset, tmp_path / "gpu", point_config, log=lambda m: None, device="cuda")
    assert whole["device"] == "cuda" and 5 < whole["val_psnr"] < 60
    if (dataset / "gt" / "views").is_dir():  # a synth subject: its novel views are scored on the GPU too
        assert any(k.startswith("novel_yaw") for k in whole), sorted(whole)
    state, r, val, on_gpu = kill_on_gpu_resume_on_cpu("pointavatar", dataset, tmp_path / "run", point_config,
                                                      interrupt_after)
    assert [row[0] for row in state["points"]] == [2, 3, 4]
    avatar, config = r.avatar, r.config
    cams = Cameras.at_origin(val.K.cuda(), 1, config.resolution)
    params = {k: v[:1] for k, v in avatar.frame_params(torch.tensor([0])).items()}
    with torch.no_grad():
        relit_gpu = avatar.render(params, cams, light={"direction": torch.tensor([0.0, 0.5, 1.0])}).rgb.cpu()
    avatar = avatar.cpu()
    on_cpu = score(r.method, avatar, val, config)[0]
    assert abs(on_gpu["psnr"] - on_cpu["psnr"]) < 0.05, (on_gpu, on_cpu)
    params = {k: v[:1] for k, v in avatar.frame_params(torch.tensor([0])).items()}
    with torch.no_grad():
        relit_cpu = avatar.render(params, Cameras.at_origin(val.K, 1, config.resolution),
                                  light={"direction": torch.tensor([0.0, 0.5, 1.0])}).rgb
    assert (relit_gpu - relit_cpu).abs().mean() < 1e-3


def test_headcraft_trains_on_cuda_draws_the_cpus_numbers_and_resumes_on_the_cpu(tmp_path):
    """Every model of ``craft train`` runs on the GPU; StyleGAN2 draws its latents from the CPU's
    generator, so its first losses on either device agree; a GPU checkpoint resumes on the CPU."""
    from test_craft_generative import TINY, cli, write_map_folder

    from headforge.craft.generative import train as T
    from headforge.craft.pipeline import template_for

    maps = write_map_folder(tmp_path / "maps", template_for("open-head", 1), ["id000", "id001", "id002", "id003", "id004"])
    for device in ("cuda", "cpu"):
        r = cli("craft", "train", maps, "-o", tmp_path / device, "--model", "stylegan2", "--steps", 1, "--device",
                device, *TINY)
        assert r.exit_code == 0, r.output
    first = {d: json.loads((tmp_path / d / "run.json").read_text())["methods"]["stylegan2"]["last_losses"]
             for d in ("cuda", "cpu")}
    for k in first["cpu"]:
        assert first["cuda"][k] == pytest.approx(first["cpu"][k], rel=2e-2, abs=1e-4), (k, first)
    r = cli("craft", "train", maps, "-o", tmp_path / "all", "--model", "all", "--steps", 3, "--device", "cuda", *TINY)
    assert r.exit_code == 0, r.output
    r = cli("craft", "train", maps, "-o", tmp_path / "all", "--model", "stylegan2", "--steps", 5, "--device", "cpu", *TINY)
    assert r.exit_code == 0 and "resuming at step 3" in r.output, r.output
    trainer, _ = T.load_trained(tmp_path / "all", "vqvae")
    T.move(trainer, "cuda")
    assert T.sample_latents("vqvae", trainer, 2, 1.0, torch.Generator().manual_seed(0)).device.type == "cpu"
