"""Avatar training over processes (headforge.distributed, gloo on the CPU): a 2-process step's
network gradients equal the single-process gradients of the same global batch, and a 2-process
run resumed from a single-process checkpoint follows the single-process run.

The processes are spawned with torch.multiprocessing and meet through a file (no ports). NHA's
quick preset at the tiny sizes of tests/data/make_nha_reference.py, with two of its terms off:
``surface`` compares the first two frames of a batch (a pair split over ranks is not compared)
and ``rgb`` is normalised by the batch's pixel count (per rank under DDP); every other term is a
mean over the batch's frames, for which DDP's averaged gradient is the global batch's gradient.
docs/batch_and_distributed.md says what this means for a run.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parent / "data"))

WORLD = 2
TINY_CLI = Path(__file__).parent / "data" / "tiny_cli.py"
STAGES = {"geometry": {"w_surface": 0.0}, "joint": {"w_surface": 0.0, "w_rgb": 0.0}}


def _config(settings: dict):
    from make_nha_reference import reference_settings

    from headforge.avatars.nha.config import NHAConfig

    config = NHAConfig.quick()
    for k, v in (reference_settings() | settings).items():
        setattr(config, k, v)
    return config


def _join(rank: int, init_file: str) -> None:
    import torch.distributed as dist

    from make_nha_reference import use_tiny_head

    torch.set_num_threads(1)
    use_tiny_head()
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)


def _gradients(dataset: Path, stage: str, settings: dict, rows: torch.Tensor) -> dict[str, torch.Tensor]:
    """The gradients of one training step of ``stage`` on the global batch ``rows``."""
    from headforge.avatars.engine import backward_step
    from headforge.avatars.frames import FrameData
    from headforge.avatars.nha.method import NHAMethod
    from headforge.avatars.run import RunAssets
    from headforge.metrics.protocol import TrackedHead

    config = _config(settings)
    torch.manual_seed(config.seed)  # as the engine seeds before building: the same initial weights
    assets = RunAssets.from_dataset(dataset)
    method = NHAMethod()
    avatar = method.build(assets, config)
    train = FrameData(dataset, "train", config.resolution, TrackedHead(assets.head_data(), assets.tracking["shape"]))
    backward_step(method, avatar, method.optimisers(avatar, config), train, rows, config, stage)
    return {n: p.grad.detach().clone() for n, p in avatar.named_parameters() if p.grad is not None}


def _gradient_worker(rank: int, init_file: str, dataset: Path, rows: torch.Tensor, out: Path) -> None:
    import torch.distributed as dist

    _join(rank, init_file)
    try:
        grads = {stage: _gradients(dataset, stage, settings | {"batch": len(rows)}, rows)
                 for stage, settings in STAGES.items()}
        if rank == 0:
            torch.save(grads, out)
    finally:
        dist.destroy_process_group()


def _differs(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest difference relative to the tensor's largest magnitude."""
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-30))


def test_two_process_gradients_equal_the_single_process_gradients(rendered, tiny_head, tmp_path):
    import torch.multiprocessing as mp

    rows = torch.tensor([3, 0, 4, 1])  # a global batch of 4 training frames: 2 per rank
    out = tmp_path / "ddp_grads.pt"
    mp.spawn(_gradient_worker, args=(str(tmp_path / "init"), rendered, rows, out), nprocs=WORLD)
    ddp = torch.load(out)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for stage, settings in STAGES.items():
            single = _gradients(rendered, stage, settings | {"batch": 4}, rows)
            half = _gradients(rendered, stage, settings | {"batch": 2}, rows[:2])  # what rank 0 alone computes
            assert ddp[stage].keys() == single.keys()
            networks = [n for n in single if not n.startswith("frames.")]
            assert any(n.startswith("geometry_net.") for n in networks)
            if stage == "joint":
                assert any(n.startswith("texture_net.") for n in networks)
            for name, g in single.items():
                # float32 all-reduce against one process's sum: 1.2e-5 on an AMD EPYC host
                assert _differs(ddp[stage][name], g) < 1e-4, (stage, name, _differs(ddp[stage][name], g))
            # not a comparison that cannot fail: one rank's share alone gives other gradients
            assert max(_differs(half[n], single[n]) for n in networks) > 1e-2
            # a frame's parameters get their gradient from the rank holding the frame, scaled as
            # the global batch's mean
            expression = ddp[stage]["frames.expression"]
            assert expression[rows].abs().sum(1).gt(0).all() and expression[[2]].abs().sum() == 0
    finally:
        torch.set_num_threads(threads)


def _losses(run: Path) -> list[list[str]]:
    return list(csv.reader((run / "losses.csv").read_text().splitlines()))


@pytest.mark.slow  # three tiny runs, one of them on two processes: ~1 min on 2 quiet cores
def test_a_two_process_run_resumes_a_checkpoint_and_follows_the_single_process_run(tiny_head, tmp_path, interrupt_after):
    """A run killed in its third iteration (checkpoint at 2), resumed by ``torchrun
    --nproc-per-node 2 ... fit``, ends like the same run on one process: the same losses, weights and fitted frames (the alignment after
    the geometry stage and the test-time fitting shared by the ranks); rank 0 alone wrote."""
    from safetensors.torch import load_file

    from conftest import write_rendered_dataset
    from make_nha_reference import reference_settings
    from headforge.avatars.engine import fit

    # 12 training frames: per-frame fitting deals two batches of 8 and 4 frames to the two ranks
    dataset = write_rendered_dataset(tmp_path / "data", tiny_head, frames=16, val=4)
    settings = STAGES["geometry"] | {"w_rgb": 0.0, "batch": 2, "geometry_iters": 4, "texture_iters": 2, "joint_iters": 4,
                                     "checkpoint_every": 2, "val_every": 5, "tto_steps": 2}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fit("nha", dataset, tmp_path / "single", _config(settings), log=lambda m: None)
        with pytest.raises(KeyboardInterrupt):
            fit("nha", dataset, tmp_path / "ddp", _config(settings), log=lambda m: None, progress=interrupt_after(3))
    finally:
        torch.set_num_threads(threads)
    # the command line under torchrun (rendezvous on a free local port), as a user runs it
    sets = [a for k, v in (reference_settings() | settings).items() for a in ("--set", f"{k}={v}")]
    torchrun = Path(sys.executable).with_name("torchrun")
    res = subprocess.run([str(torchrun), "--standalone", "--nproc-per-node", str(WORLD), str(TINY_CLI), "fit", "nha",
                          str(dataset), "-o", str(tmp_path / "ddp"), "--device", "cpu", *sets],
                         capture_output=True, text=True, env=os.environ | {"OMP_NUM_THREADS": "1"}, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    printed = [line for line in res.stdout.splitlines() if line.startswith("{")]
    assert len(printed) == 1 and json.loads(printed[0])["method"] == "nha"  # rank 0 alone prints

    # The step's arithmetic is the same (the test above); float rounding in a different order,
    # which Adam's normalised steps amplify where a gradient is near zero, leaves ~1e-3 drift.
    single, ddp = _losses(tmp_path / "single"), _losses(tmp_path / "ddp")
    assert [r[0] for r in ddp] == [str(i) for i in range(1, 11)]  # written once, by rank 0
    for a, b in zip(single, ddp):
        assert a[1] == b[1] and float(b[3]) == pytest.approx(float(a[3]), rel=1e-2), (a, b)
    want, got = load_file(tmp_path / "single" / "checkpoint.safetensors"), load_file(tmp_path / "ddp" / "checkpoint.safetensors")
    assert want.keys() == got.keys()
    for name in want:
        if not torch.isfinite(want[name]).all() or not want[name].is_floating_point():
            assert torch.equal(got[name], want[name]), name
        elif want[name].abs().max() > 0:
            drift = float((got[name] - want[name]).norm() / want[name].norm())
            assert drift < 2e-2, (name, drift)
    a, b = (json.loads((tmp_path / r / "metrics.json").read_text()) for r in ("single", "ddp"))
    assert b["val_psnr"] == pytest.approx(a["val_psnr"], abs=0.02)
    assert (tmp_path / "ddp" / "progress.png").is_file() and (tmp_path / "ddp" / "val_worst.png").is_file()


def _helpers_worker(rank: int, init_file: str, out: Path) -> None:
    import torch.distributed as dist

    from headforge import distributed
    from headforge.errors import HeadforgeError

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    try:
        result = {"rank": distributed.rank(), "main": distributed.is_main(), "world": distributed.world_size()}
        result["share"] = distributed.shard(torch.arange(6)).tolist()
        try:
            distributed.shard(torch.arange(3))
        except HeadforgeError as exc:
            result["uneven"] = str(exc)
        # a: used by both ranks; b: only by rank 1's items; c: by nobody
        a, b, c = (torch.nn.Parameter(torch.zeros(2)) for _ in range(3))
        a.grad = torch.full((2,), float(rank + 1))
        if rank == 1:
            b.grad = torch.tensor([4.0, -2.0])
        distributed.average_gradients([a, b, c])
        result["grads"] = [a.grad.tolist(), b.grad.tolist(), c.grad]
        flags = torch.nn.Module()
        flags.register_buffer("seen", torch.tensor([rank == 0, rank == 1, False]))
        distributed.combine_flags(flags)
        result["flags"] = flags.seen.tolist()
        table = {"x": torch.full((4, 2), float(rank)), "y": torch.full((4,), 10.0 * rank)}
        rows = torch.tensor([0, 1, 3])
        distributed.merge_rows(table, rows, torch.tensor([rank == 0, rank == 1, rank == 1]))
        result["merged"] = [table["x"][:, 0].tolist(), table["y"].tolist()]
        result["terms"] = {k: float(v) for k, v in distributed.mean_terms({"l": torch.tensor(float(rank))}).items()}
        result["owned"] = distributed.owned(5)
        result["object"] = distributed.broadcast_object({"from": rank})
        # a torchrun rank on the CPU: numba's kernels take the process's torch threads, not every core
        import numba

        os.environ |= {"WORLD_SIZE": str(WORLD), "LOCAL_RANK": str(rank)}
        torch.set_num_threads(1)
        result["device"] = str(distributed.init_from_environment("cpu"))
        result["numba_threads"] = numba.get_num_threads()
        torch.save(result, out / f"{rank}.pt")
    finally:
        dist.destroy_process_group()


def test_the_distributed_helpers(tmp_path):
    """average_gradients (gradients on some ranks only), combine_flags, merge_rows, shard,
    owned, mean_terms, broadcast_object on 2 gloo processes; all no-ops without a group."""
    import torch.multiprocessing as mp

    from headforge import distributed

    mp.spawn(_helpers_worker, args=(str(tmp_path / "init"), tmp_path), nprocs=WORLD)
    r0, r1 = (torch.load(tmp_path / f"{r}.pt") for r in range(WORLD))
    assert (r0["main"], r1["main"], r0["world"]) == (True, False, 2)
    assert r0["share"] == [0, 1, 2] and r1["share"] == [3, 4, 5]
    assert "cannot be split evenly over 2 processes" in r0["uneven"]
    for r in (r0, r1):
        assert r["grads"] == [[1.5, 1.5], [2.0, -1.0], None]  # b: rank 1's gradient / 2, on both ranks
        assert r["flags"] == [True, True, False]
        # row 0 from rank 0, rows 1 and 3 from rank 1, row 2 (nobody's) left as it was
        assert r["merged"][0][:2] == [0.0, 1.0] and r["merged"][0][3] == 1.0
        assert r["merged"][1][:2] == [0.0, 10.0] and r["merged"][1][3] == 10.0
        assert r["terms"] == {"l": 0.5} and r["object"] == {"from": 0}
    assert r0["owned"] == [0, 2, 4] and r1["owned"] == [1, 3]
    assert r0["device"] == r1["device"] == "cpu" and r0["numba_threads"] == r1["numba_threads"] == 1
    # without a process group: one rank, nothing to do
    assert not distributed.active() and distributed.is_main() and distributed.world_size() == 1
    rows = torch.arange(3)
    assert distributed.shard(rows) is rows and distributed.owned(3) == [0, 1, 2]


POINT_SETTINGS = dict(resolution=64, iterations=12, init_points=300, upsample_every=5, prune_every=4, max_points=2000,
                      canonical_width=32, canonical_layers=3, canonical_skip=2, frequencies=2, deformer_width=32,
                      deformer_layers=2, shading_width=16, val_every=6, checkpoint_every=4, val_frames=2, tto_steps=2,
                      tto_photometric_steps=0, val_tto_steps=1, points_per_pixel=4)


@pytest.mark.slow  # two tiny PointAvatar runs through the command line: ~1 min on 2 quiet cores
def test_pointavatar_on_two_processes_prunes_and_doubles_as_on_one(tiny_head, tmp_path):
    """Pruning reads the points' visibility, which each rank gathers from its own frames: OR-ed
    over the ranks it is the single-process visibility, so the point counts match exactly."""
    from conftest import write_rendered_dataset

    dataset = write_rendered_dataset(tmp_path / "data", tiny_head, frames=12, val=4)
    sets = [a for k, v in POINT_SETTINGS.items() for a in ("--set", f"{k}={v}")]
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    torchrun = [str(Path(sys.executable).with_name("torchrun")), "--standalone", "--nproc-per-node", str(WORLD)]
    for launcher, run in (([sys.executable], "single"), (torchrun, "ddp")):
        res = subprocess.run([*launcher, str(TINY_CLI), "fit", "pointavatar", str(dataset), "-o", str(tmp_path / run),
                              "--device", "cpu", *sets], capture_output=True, text=True, env=env, timeout=600)
        assert res.returncode == 0, res.stderr[-3000:]
    single, ddp = (json.loads((tmp_path / r / "state.json").read_text()) for r in ("single", "ddp"))
    assert ddp["points"] == single["points"] and ddp["pruned"] == single["pruned"]
    assert len(single["pruned"]) == 2 and len(single["points"]) == 4  # the schedule ran: 2 prunes, 2 doublings
    a, b = (json.loads((tmp_path / r / "metrics.json").read_text()) for r in ("single", "ddp"))
    assert b["val_psnr"] == pytest.approx(a["val_psnr"], abs=0.05)
    assert (tmp_path / "ddp" / "points.png").is_file()  # the method's pictures, by rank 0
