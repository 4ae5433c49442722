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


def test_fit_on_cuda_checkpoints_and_resumes_on_the_cpu(dataset, tiny_config, tmp_path, interrupt_after):
    from headforge.avatars.engine import fit, score
    from headforge.avatars.frames import FrameData
    from headforge.avatars.run import load_run
    from headforge.metrics.protocol import TrackedHead

    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        fit("nha", dataset, run, tiny_config, log=lambda m: None, progress=interrupt_after(5), device="cuda")
    state = json.loads((run / "state.json").read_text())
    assert state["iteration"] == 4 and state["aligned"] > 0
    metrics = fit("nha", dataset, run, tiny_config, log=lambda m: None, device="cpu")
    assert metrics["device"] == "cpu" and 5 < metrics["val_psnr"] < 60
    r = load_run(run, "cuda")
    avatar, config = r.avatar, r.config
    assert next(avatar.parameters()).is_cuda
    val = FrameData(dataset, "val", config.resolution, TrackedHead(r.assets.head_data(), r.assets.tracking["shape"]))
    on_gpu = score(r.method, avatar, copy.deepcopy(val).to("cuda"), config)[0]
    on_cpu = score(r.method, avatar.cpu(), val, config)[0]
    assert abs(on_gpu["psnr"] - on_cpu["psnr"]) < 0.05, (on_gpu, on_cpu)
