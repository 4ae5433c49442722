"""HeadCraft part 2 benchmark: train StyleGAN2 and the baselines on a registered scan set, score
them on held-out registrations (HeadCraft Tables 1-2) and check memorisation (Fig. 5).

    # the data (part 1): a training and a held-out scan set, registered at 64 px
    headforge craft scans -o TRAIN_SCANS --n 10 --seed 0 --no-harder
    headforge craft scans -o HELD_SCANS --n 5 --seed 100 --no-harder
    headforge craft register TRAIN_SCANS -o TRAIN_MAPS --map-size 64 --steps-scale 0.25
    headforge craft register HELD_SCANS -o HELD_MAPS --map-size 64 --steps-scale 0.25
    # train (resumable) + evaluate
    python benchmarks/bench_craft_generate.py --maps TRAIN_MAPS --heldout HELD_MAPS --out RUN \\
        [--steps stylegan2=3000,vae=1500,vqvae=1000] [--points 2048] [--seeds 3]

``--steps`` defaults to the quick preset's step counts; pass fewer to fit a time budget (the
recorded figures in docs/headcraft.md say which). With --heldout every identity of --maps
trains; without it, --holdout (0.3) of the --maps identities are held out and scored. Prints the table and a final JSON line with
``train_minutes`` (StyleGAN2's), ``mmd``, ``cov``, ``one_nna``, ``jsd`` (StyleGAN2), ``mmd_pca``,
``cov_pca``, the other models' MMD/COV, and the memorisation figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", required=True, help="training map folder (headforge craft register output)")
    ap.add_argument("--heldout", default=None, help="held-out map folder (other identities); default: the identities "
                    "--holdout leaves out of --maps")
    ap.add_argument("--holdout", type=float, default=None, help="fraction of --maps identities held out "
                    "(default 0 with --heldout, else 0.3)")
    ap.add_argument("--out", required=True, help="run folder (resumable)")
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--models", default="stylegan2,pca,vae,vqvae")
    ap.add_argument("--steps", default="", help="per-model step counts, e.g. stylegan2=600,vae=400")
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--truncation", type=float, default=1.0)
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    from headforge.craft.generative import evaluate as E
    from headforge.craft.generative import train as T
    from headforge.errors import HeadforgeError

    steps = dict(kv.split("=") for kv in args.steps.split(",") if kv)
    methods = args.models.split(",")
    holdout = args.holdout if args.holdout is not None else (0.0 if args.heldout else 0.3)
    heldout = args.heldout or args.maps
    try:
        base = T.TrainOptions(preset=args.preset, holdout=holdout, seed=0)
        T.prepare_run(args.maps, args.out, methods, base)
        t0 = time.time()
        for m in methods:
            opts = T.TrainOptions(preset=args.preset, holdout=holdout, seed=0, steps=int(steps[m]) if m in steps else None)
            T.train_method(args.out, m, opts, log=lambda s: print(s, file=sys.stderr))
        print(f"training wall time this call: {(time.time() - t0) / 60:.1f} min", file=sys.stderr)
        result = E.evaluate(args.out, heldout, methods + ["bare"], tuple(range(args.seeds)), args.points,
                            args.truncation, log=lambda s: print(s, file=sys.stderr))
    except HeadforgeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    E.write(result, Path(args.out) / "eval.json")
    print(E.table(result))
    meta = T.read_run(args.out)
    rows = result["rows"]
    sg = rows.get("stylegan2", {})
    line = {"train_minutes": meta["methods"].get("stylegan2", {}).get("train_minutes"),
            "stylegan2_steps": meta["methods"].get("stylegan2", {}).get("steps"),
            "mmd": sg.get("mmd"), "cov": sg.get("cov"), "one_nna": sg.get("one_nna"), "jsd": sg.get("jsd"),
            "mmd_pca": rows.get("pca", {}).get("mmd"), "cov_pca": rows.get("pca", {}).get("cov")}
    for m in ("vae", "vqvae", "bare"):
        if m in rows:
            line[f"mmd_{m}"], line[f"cov_{m}"] = rows[m]["mmd"], rows[m]["cov"]
    line.update({"memo_sample_nn_mm": sg.get("memo_sample_nn_mm"), "memo_heldout_nn_mm": result["heldout_nn_mm"],
                 "memo_frac_below_heldout_min": sg.get("memo_frac_below_heldout_min"),
                 "n_train": result["n_train"], "n_heldout": result["n_heldout"], "resolution": result["resolution"],
                 "points": args.points, "seeds": args.seeds})
    print(json.dumps(line))
    return 0


if __name__ == "__main__":
    sys.exit(main())
