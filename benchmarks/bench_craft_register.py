"""HeadCraft part 1 benchmark: register a held-out generated scan set (and the real scans).

    python benchmarks/bench_craft_register.py [--scans DIR | --n 5 --seed 100] [--real] [--ablation K]

Without --scans a set is generated (anny identities, seed 100: not the seeds used for tuning).
Prints per-row tables (face, per hair style, per variant; stage 1 / stage 2; Fig. 10 ablation on
the first K scans with --ablation K; real scans with --real) and a final JSON line with
``register_seconds_per_scan``, ``stage2_face_median_mm``, ``stage2_hair_median_mm``,
``roundtrip_median_mm``. Distances scan -> registered, mm; medians over scans of per-scan medians.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

SHARED_SCANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "scans"


def _med(values):
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(values)) if values else float("nan")


def _rows(results: list[dict], key_fn) -> dict:
    groups: dict[str, list[dict]] = {}
    for r in results:
        for k in key_fn(r):
            groups.setdefault(k, []).append(r)
    return groups


def _row(name: str, items: list[dict], stage: str | None = None) -> dict:
    def get(m, part, stat):
        src = m if stage is None else m.get(stage, {})
        return src.get("scan_to_reg", {}).get(part, {}).get(stat)

    return {"row": name, "n": len(items),
            "face_med": _med([get(m, "face", "median_mm") for m in items]),
            "face_p95": _med([get(m, "face", "p95_mm") for m in items]),
            "hair_med": _med([get(m, "hair", "median_mm") for m in items]),
            "hair_p95": _med([get(m, "hair", "p95_mm") for m in items]),
            "r2s_face_med": _med([m.get("reg_to_scan", {}).get("face", {}).get("median_mm") for m in items]) if stage is None else float("nan"),
            "r2s_scalp_med": _med([m.get("reg_to_scan", {}).get("scalp", {}).get("median_mm") for m in items]) if stage is None else float("nan"),
            "edge_ratio_max": float(np.max([(m if stage is None else m.get(stage, {})).get("max_edge_ratio", np.nan) for m in items])),
            "lmk_mm": _med([m.get("landmark_consistency_mm") for m in items]) if stage is None else float("nan")}


def _print(rows: list[dict], title: str) -> None:
    print(f"\n{title}")
    cols = list(rows[0])
    print("  ".join(f"{c:>13}" for c in cols))
    for r in rows:
        print("  ".join(f"{r[c]:>13.3f}" if isinstance(r[c], float) else f"{r[c]!s:>13}" for c in cols))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=Path, help="an existing scan set (else one is generated)")
    ap.add_argument("--n", type=int, default=5)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--map-size", type=int, default=256)
    ap.add_argument("--out", type=Path, help="output folder (kept; resumable)")
    ap.add_argument("--ablation", type=int, default=0, help="Fig. 10 ablation on the first K scans")
    ap.add_argument("--real", action="store_true", help=f"also register {SHARED_SCANS}")
    ap.add_argument("--only-real", action="store_true")
    args = ap.parse_args()

    from headforge.batch import run_batch
    from headforge.craft.pipeline import list_scans, register_item
    from headforge.craft.scans import ScanSetConfig, generate_scans

    out = args.out or Path(tempfile.mkdtemp(prefix="bench_craft_"))
    opts = {"preset": args.preset, "map_size": args.map_size}
    summary = {}
    results = []
    if not args.only_real:
        scans = args.scans
        if scans is None:
            scans = out / "scans"
            generate_scans(scans, ScanSetConfig(n=args.n, seed=args.seed), log=lambda m: print(m, file=sys.stderr))
        items = list_scans(scans)
        batch = run_batch([(k, {"path": p, **opts}) for k, p in items], register_item, out / "maps",
                          log=lambda m: print(m, file=sys.stderr))
        for r in batch.ok:
            results.append(json.loads((out / "maps" / r.key / "metrics.json").read_text()))
        print(f"{len(batch.ok)} of {len(items)} scans registered; failed: {[r.key for r in batch.failed]}")
        if not results:
            raise SystemExit("nothing registered")
        rows = [_row("all (stage 2)", results), _row("all (stage 1)", results, "stage1")]
        for k, v in sorted(_rows(results, lambda m: [f"style:{m['hair_style']}"]).items()):
            rows.append(_row(k, v))
        for k, v in sorted(_rows(results, lambda m: [f"variant:{m['variant']}"]).items()):
            rows.append(_row(k, v))
        harder = [m for m in results if m["variant"] != "clean"]
        if harder:
            rows.append(_row("harder (all)", harder))
        _print(rows, "scan -> registered (mm, medians over scans), registered -> scan, spike, consistency")
        summary.update({
            "register_seconds_per_scan": _med([m["seconds"] for m in results]),
            "stage2_face_median_mm": rows[0]["face_med"], "stage2_hair_median_mm": rows[0]["hair_med"],
            "stage2_face_p95_mm": rows[0]["face_p95"], "stage2_hair_p95_mm": rows[0]["hair_p95"],
            "stage1_face_median_mm": rows[1]["face_med"], "stage1_hair_median_mm": rows[1]["hair_med"],
            "harder_face_median_mm": _row("h", harder)["face_med"] if harder else None,
            "harder_hair_median_mm": _row("h", harder)["hair_med"] if harder else None,
            "max_edge_ratio": rows[0]["edge_ratio_max"], "landmark_consistency_mm": rows[0]["lmk_mm"],
            "roundtrip_median_mm": _med([m["roundtrip"]["median_mm"] for m in results]),
            "roundtrip_p95_mm": _med([m["roundtrip"]["p95_mm"] for m in results]),
            "map_size": args.map_size, "vertices": results[0]["vertices"], "scans": len(results), "preset": args.preset})
        if args.ablation:
            abl_rows = []
            sub = items[:args.ablation]
            for mode in ("stage1", "stage2", "both", "stage1_weights2"):
                if mode == "both":  # the main run is this configuration: reuse it
                    keys = {k for k, _ in sub}
                    ms = [m for r, m in zip(batch.ok, results) if r.key in keys]
                else:
                    b = run_batch([(k, {"path": p, **opts, "ablation": mode}) for k, p in sub], register_item,
                                  out / f"ablation_{mode}", log=lambda m: print(m, file=sys.stderr))
                    ms = [json.loads((out / f"ablation_{mode}" / r.key / "metrics.json").read_text()) for r in b.ok]
                if ms:
                    abl_rows.append(_row(mode, ms))
                hard = [m for m in ms if m["variant"] != "clean"]
                if hard:
                    abl_rows.append(_row(f"{mode} (harder)", hard))
            _print(abl_rows, f"Fig. 10 ablation on {args.ablation} scans")
            summary["ablation"] = {r["row"]: {"face_med": r["face_med"], "face_p95": r["face_p95"], "hair_med": r["hair_med"],
                                              "hair_p95": r["hair_p95"], "edge_ratio_max": r["edge_ratio_max"]} for r in abl_rows}
    if args.real or args.only_real:
        if not SHARED_SCANS.exists():
            print(f"no real scans at {SHARED_SCANS}; skipped")
        else:
            real = [(p.stem, str(p)) for p in sorted(SHARED_SCANS.glob("*.obj"))]
            b = run_batch([(k, {"path": p, **opts}) for k, p in real], register_item, out / "real",
                          log=lambda m: print(m, file=sys.stderr))
            rr = []
            for r in b.items:
                if r.status == "failed":
                    rr.append({"row": r.key, "error": r.error})
                    continue
                m = json.loads((out / "real" / r.key / "metrics.json").read_text())
                s = m["scan_to_reg"]
                rr.append({"row": r.key, "s2r_head_med": s["head"]["median_mm"], "s2r_head_p95": s["head"]["p95_mm"],
                           "s2r_all_med": s["all"]["median_mm"], "r2s_face_med": m["reg_to_scan"]["face"]["median_mm"],
                           "edge_ratio": m["max_edge_ratio"], "seconds": m["seconds"],
                           "landmarks": m["scan"].get("landmarks", "")})
            print("\nreal scans (no ground truth): scan -> registered over the head (above the lower neck), mm")
            for r in rr:
                print(json.dumps(r))
            summary["real"] = rr
    print(json.dumps(summary, default=float))


if __name__ == "__main__":
    main()
