"""HeadCraft's StyleGAN2 training over processes (headforge.distributed, gloo on the CPU): one
step's generator and discriminator gradients on 2 processes equal a single process's at the same
global batch, with every term on (the logistic losses, R1 and path length, both due at step 0).

Each rank takes a strided share of the batch (items rank, rank + 2, ...), so with a global batch
of 8 the minibatch-std groups of 4 are the single process's ({0, 2, 4, 6} and {1, 3, 5, 7})
and every term is a mean over items. The learning rates are 0: the generator's gradient is taken
against the discriminator after its step, and Adam's normalised first step would amplify float
rounding where a gradient is near zero. Processes are spawned with torch.multiprocessing and
meet through a file (no ports). Tiny 32 x 32 maps and networks.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

WORLD = 2
BATCH = 8


def _config():
    from headforge.craft.generative.stylegan2 import StyleGAN2Config

    return StyleGAN2Config(resolution=32, z_dim=16, w_dim=16, mapping_layers=2, channel_base=256, channel_max=16,
                           batch=BATCH, g_lr=0.0, d_lr=0.0, mbstd_group=4)


def _real() -> torch.Tensor:
    """The global batch (8, 3, 32, 32), the same on every rank."""
    return torch.randn(BATCH, 3, 32, 32, generator=torch.Generator().manual_seed(5)) * 0.5


def _step() -> dict[str, torch.Tensor]:
    """Gradients (G.*, D.*) and the statistics (pl_mean, w_avg) after one training step."""
    from headforge.craft.generative.stylegan2 import StyleGAN2Trainer

    trainer = StyleGAN2Trainer(_config(), None, seed=3)
    logs = trainer.train_step(_real())
    assert {"r1", "pl", "loss_d", "loss_g"} <= logs.keys()  # both regularisers were in the step
    out = {f"{net}.{n}": p.grad.detach().clone() for net, module in (("G", trainer.G), ("D", trainer.D))
           for n, p in module.named_parameters()}
    out["pl_mean"] = trainer.pl_mean.reshape(1).clone()
    out["w_avg"] = trainer.G.mapping.w_avg.clone()
    return out


def _worker(rank: int, init_file: str, out: str) -> None:
    import torch.distributed as dist

    from headforge import distributed

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    try:
        averaged = _step()
        average = distributed.average_gradients
        distributed.average_gradients = lambda parameters: None  # each rank keeps its own share's gradient
        try:
            alone = _step()
        finally:
            distributed.average_gradients = average
        torch.save({"averaged": averaged, "alone": alone}, f"{out}.{rank}")
    finally:
        dist.destroy_process_group()


def _differs(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest difference relative to the tensor's largest magnitude."""
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-30))


def test_two_process_stylegan2_gradients_equal_the_single_process_gradients(tmp_path):
    import torch.multiprocessing as mp

    mp.spawn(_worker, args=(str(tmp_path / "init"), str(tmp_path / "grads")), nprocs=WORLD)
    ranks = [torch.load(tmp_path / f"grads.{r}") for r in range(WORLD)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        single = _step()
    finally:
        torch.set_num_threads(threads)
    assert any(n.startswith("G.mapping.") for n in single) and any(n.startswith("D.blocks.") for n in single)
    for r in ranks:
        assert r["averaged"].keys() == single.keys()
        for name, want in single.items():
            assert _differs(r["averaged"][name], want) < 1e-4, (name, _differs(r["averaged"][name], want))
    # not a comparison that cannot fail: one rank's share alone gives other gradients
    nets = [n for n in single if n.startswith(("G.", "D."))]
    for r in ranks:
        assert max(_differs(r["alone"][n], single[n]) for n in nets if n.startswith("G.")) > 1e-2
        assert max(_differs(r["alone"][n], single[n]) for n in nets if n.startswith("D.")) > 1e-2



TINY = ["--set", "resolution=32", "--set", "channel_base=128", "--set", "channel_max=16", "--set", "z_dim=16",
        "--set", "w_dim=16", "--set", "batch=8", "--set", "widths=8,8,8", "--set", "strides=1,2,2"]


def _flat(checkpoint: Path) -> torch.Tensor:
    """Every float tensor of a StyleGAN2 checkpoint (G, D, G_ema) in one vector."""
    from safetensors.torch import load_file

    tensors = load_file(checkpoint)
    return torch.cat([tensors[k].reshape(-1) for k in sorted(tensors) if k.split(".")[0] in ("G", "D", "G_ema")])


@pytest.mark.slow  # a map folder, two single-process and two torchrun runs, a refused one: ~45 s on 2 quiet cores
def test_craft_train_under_torchrun_follows_the_single_process_run(tmp_path):
    """``torchrun --nproc-per-node 2 ... craft train``: rank 0 alone logs and writes; 2 steps, then
    resumed to 4, end within 0.1 % of what steps 3-4 moved the single process's weights (measured:
    ~5e-6 of it; float rounding). Batch 8: each share holds a whole minibatch-std group of 4 (with
    batch 4 the groups shrink to the shares of 2 and the 2-step weights were 26 % of that movement
    apart). The VQ-VAE is refused with a one-line error."""
    from headforge.craft.pipeline import template_for
    from test_craft_generative import write_map_folder

    maps = write_map_folder(tmp_path / "maps", template_for("open-head", 1), ["id000", "id001", "id002", "id003", "id004"])
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    torchrun = [str(Path(sys.executable).with_name("torchrun")), "--standalone", "--nproc-per-node", str(WORLD)]
    weights = {}
    for name, launcher in (("single", [sys.executable]), ("ddp", torchrun)):
        for steps in ("2", "4"):  # the second resumes the first's checkpoint
            res = subprocess.run([*launcher, "-m", "headforge.cli", "craft", "train", str(maps), "-o", str(tmp_path / name),
                                  "--model", "stylegan2", "--steps", steps, *TINY],
                                 capture_output=True, text=True, env=env, timeout=300)
            assert res.returncode == 0, res.stderr[-3000:]
            assert res.stdout.count(f"stylegan2: {steps} steps") == 1, res.stdout  # rank 0 alone logs
            weights[name, steps] = _flat(tmp_path / name / "stylegan2" / "checkpoint.safetensors")
        assert "resuming at step 2" in res.stdout
    ck = json.loads((tmp_path / "ddp" / "stylegan2" / "checkpoint.json").read_text())
    assert (ck["step"], ck["images"], ck["done"]) == (4, 32, True)
    moved = float((weights["single", "4"] - weights["single", "2"]).norm())
    assert moved > 0
    for steps in ("2", "4"):
        drift = float((weights["ddp", steps] - weights["single", steps]).norm())
        assert drift < 1e-3 * moved, (steps, drift, moved)
    res = subprocess.run([*torchrun, "-m", "headforge.cli", "craft", "train", str(maps), "-o", str(tmp_path / "vq"),
                          "--model", "vqvae", "--steps", "1", *TINY], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode != 0 and "error: vqvae trains on one process only" in res.stdout + res.stderr
