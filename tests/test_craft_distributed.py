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

import torch

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
