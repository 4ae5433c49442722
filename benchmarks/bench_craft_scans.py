"""HeadCraft part 1: cost of a generated scan's hair volume, banded against full evaluation.

    python benchmarks/bench_craft_scans.py [--voxel 0.003] [--repeats 2] [--threads 1]

The hair volume (a signed-distance grid of the hair style, meshed by marching cubes) is what a
generated scan costs (`headforge craft scans`). For each hair style, on the open-head template
at two head sizes (x1.0, x1.08), it builds the volume with the banded grid evaluation
(:func:`headforge.craft.scans.banded_grid_values`, what `craft scans` uses) and with the full
grid, and reports both times (median of --repeats) and whether the meshes are identical (else
how many vertices moved, and how far). Prints a table and a final JSON line with
``banded_seconds``, ``full_seconds`` (medians over styles and sizes), ``speedup`` and
``identical`` (meshes identical / compared).
"""

from __future__ import annotations

import argparse
import json
import time
from unittest import mock

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel", type=float, default=0.003, help="hair grid voxel, m (craft scans' default)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="torch / k-d tree threads (craft scans' workers use 1)")
    args = ap.parse_args(argv)
    if not 0.001 <= args.voxel <= 0.01 or args.repeats < 1 or args.threads < 1:
        ap.error("--voxel must be within [0.001, 0.01] m, --repeats and --threads at least 1")

    import torch
    from scipy.spatial import cKDTree

    from headforge.craft import scans
    from headforge.head import load_data

    torch.set_num_threads(args.threads)
    data = load_data("open-head")
    rows = []
    for style in [s for s in scans.HAIR_STYLES if s != "bald"]:
        for scale in (1.0, 1.08):
            v = data.v_template * scale

            def build():
                return scans.build_hair_volume(style, v, data.faces, data.regions["scalp"], args.voxel, seed=3)

            times = {"banded": [], "full": []}
            for _ in range(args.repeats):
                t = time.perf_counter()
                banded = build()
                times["banded"].append(time.perf_counter() - t)
                with mock.patch.object(scans, "banded_grid_values", lambda a, e, margin: scans.full_grid_values(a, e)):
                    t = time.perf_counter()
                    full = build()
                    times["full"].append(time.perf_counter() - t)
            identical = np.array_equal(banded[0], full[0]) and np.array_equal(banded[1], full[1])
            d1 = cKDTree(full[0]).query(banded[0])[0]
            d2 = cKDTree(banded[0]).query(full[0])[0]
            rows.append({"style": style, "scale": scale, "banded_s": float(np.median(times["banded"])),
                         "full_s": float(np.median(times["full"])), "identical": identical,
                         "moved_vertices": int((d1 > 1e-9).sum() + (d2 > 1e-9).sum()),
                         "max_moved_mm": float(1000 * max(d1.max(), d2.max()))})
            r = rows[-1]
            same = "identical" if identical else f"{r['moved_vertices']} vertices moved, max {r['max_moved_mm']:.2f} mm"
            print(f"{style:>9} x{scale:<5} banded {r['banded_s']:6.1f} s  full {r['full_s']:6.1f} s  {same}", flush=True)
    banded_s = float(np.median([r["banded_s"] for r in rows]))
    full_s = float(np.median([r["full_s"] for r in rows]))
    print(json.dumps({"voxel_m": args.voxel, "threads": args.threads, "banded_seconds": banded_s, "full_seconds": full_s,
                      "speedup": full_s / banded_s, "identical": f"{sum(r['identical'] for r in rows)}/{len(rows)}",
                      "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
