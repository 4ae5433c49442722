"""How far a 2-process (gloo) NHA training step's gradients are from the single-process gradients
of the same global batch, per stage, with NHA's quick-preset terms as they are and with the two
terms that are not means over the batch's frames turned off (``surface``: the first two frames
of a batch compared; ``rgb``: normalised by the batch's pixel count).

    python benchmarks/ddp_gradients.py [--batch 4]

Tiny head model and rendered dataset of the tests (tests/conftest.py), tiny network sizes
(tests/data/make_nha_reference.py). Prints one JSON line: for each case and stage the largest
difference of a network tensor's gradient relative to that tensor's largest gradient.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "tests" / "data"))

CASES = {"per-frame terms only": {"w_surface": 0.0, "w_rgb": 0.0}, "quick preset's terms": {}}
STAGES = ("geometry", "texture", "joint")


def _worker(rank: int, init_file: str, dataset: Path, rows: torch.Tensor, out: Path) -> None:
    import torch.distributed as dist

    from test_distributed import _gradients, _join

    _join(rank, init_file)
    try:
        grads = {(case, stage): _gradients(dataset, stage, settings | {"batch": len(rows)}, rows)
                 for case, settings in CASES.items() for stage in STAGES}
        if rank == 0:
            torch.save(grads, out)
    finally:
        dist.destroy_process_group()


def main() -> None:
    import torch.multiprocessing as mp

    from conftest import write_rendered_dataset
    from make_nha_reference import use_tiny_head
    from test_distributed import WORLD, _differs, _gradients

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=4, help="global batch (a multiple of 2; the tiny dataset has 5 training frames)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    data = use_tiny_head()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        dataset = write_rendered_dataset(tmp / "data", data)
        rows = torch.randperm(5, generator=torch.Generator().manual_seed(0))[: args.batch]
        mp.spawn(_worker, args=(str(tmp / "init"), dataset, rows, tmp / "grads.pt"), nprocs=WORLD)
        ddp = torch.load(tmp / "grads.pt")
        result = {"world": WORLD, "batch": args.batch}
        for case, settings in CASES.items():
            for stage in STAGES:
                single = _gradients(dataset, stage, settings | {"batch": args.batch}, rows)
                worst = max(_differs(ddp[case, stage][n], g) for n, g in single.items() if not n.startswith("frames."))
                result[f"{case}: {stage}"] = float(f"{worst:.3g}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
