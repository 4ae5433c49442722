"""HeadCraft depth completion benchmark (issue 43; the paper's §4.4 / Fig. 8 protocol on
generated scans with exact ground truth).

For every held-out generated scan (``headforge craft scans``; harder variants included):

- three observations: a 512 px depth map from the front and one from 45 degrees (written as
  16-bit PNG + camera JSON and read back, as a user's file would be), and a 1 %-subsampled cloud
  of the frontal map (written as PLY in the sensor's frame and read back);
- one partial registration per observation, shared by the four completions: StyleGAN2
  (z -> Delta-w -> noise), PCA (MAP fit of the observed texels), the mean training map, and the
  head model alone (a zero map), each on the head model fitted to the observation;
- scores in the scan's frame against the whole scan (:func:`headforge.craft.fit.completion_scores`):
  Chamfer and one-sided distances (mm) overall, on the part the depth map saw (GT samples
  within 4 mm of the map's depth at their pixel), on the unseen part, and on the unseen back
  and hair (unseen samples labelled scalp or hair);
- ``--z-starts K --combine best|mean``: the StyleGAN2 fit from K z initialisations (the paper: one);
  ``--truncation PSI``: its z step on w pulled toward the average w (the paper: 1);
- each partial registration is kept as ``<scan>/<observation>/registration.npz`` (under
  ``--registrations DIR``, default OUT) and reused by any later run with the same observation
  settings, so a fitting variant is compared on the very same partial maps;
- with ``--full``: the full-scan fit (registration, then the whole map) beside the
  registration itself (the generator's reconstruction gap);
- a hair-transfer sheet between the first two scans' frontal completions.

Writes ``OUT/<scan>/<observation>/`` (observation file, picture.png, scores.json),
``OUT/<scan>/scan_result.json`` (a finished scan: a re-run with the same settings skips it),
``OUT/results.json``, ``OUT/table.md``; prints one JSON line of figures at the end. ``--workers N``
fits N scans at a time in separate processes (``--threads`` torch threads each).

    python benchmarks/bench_craft_fit.py --run RUN --scans HELD_SCANS -o OUT [--workers 8 --threads 1]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from headforge.craft import fit as F
from headforge.craft import observe as O
from headforge.craft.generative import invert as I
from headforge.craft.partial import partial_map, register_partial
from headforge.craft.scans import load_generated, render_mesh, write_png

METHODS = ("stylegan2", "pca", "mean", "bare")
REGIONS = ("all", "observed", "unseen", "unseen_back_hair")


def observations(scan_dir: Path, scan, gt, out: Path, size: int, side_yaw: float, cloud_fraction: float):
    """[(name, Observation, camera of the depth it came from, that depth)]"""
    import trimesh

    target = gt["landmarks"].mean(0) + np.array([0.0, -0.02, -0.04])
    result = []
    front = None
    for name, yaw in (("front", 0.0), (f"yaw{side_yaw:g}", side_yaw)):
        cam = O.depth_camera(target, yaw, size=size)
        depth = O.render_depth(scan.vertices, scan.faces, cam)
        (out / name).mkdir(parents=True, exist_ok=True)
        O.write_depth(out / name / "depth.png", depth, cam)
        obs = O.read_depth(out / name / "depth.png")
        result.append((name, obs, cam, obs.depth))
        if yaw == 0.0:
            front = (obs, cam)
    obs, cam = front
    sub = O.subsample(obs, cloud_fraction)
    name = f"cloud{100 * cloud_fraction:g}pct"
    (out / name).mkdir(parents=True, exist_ok=True)
    trimesh.PointCloud(sub.points @ sub.to_source.T).export(out / name / "cloud.ply")  # the sensor's frame
    result.append((name, O.read_cloud(out / name / "cloud.ply"), cam, obs.depth))
    return result


def to_scan_frame(obs, cam):
    """canonical -> W (alignment) -> the sensor's camera frame -> the scan's frame."""
    return lambda align, v: (align.to_scan(v) @ obs.to_source.T - cam.t) @ cam.R


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, help="run folder of headforge craft train (stylegan2 and pca trained)")
    ap.add_argument("--scans", required=True, help="held-out generated scan folders (headforge craft scans)")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--limit", type=int, default=20, help="scans to use (the issue: 20)")
    ap.add_argument("--size", type=int, default=512, help="depth map size")
    ap.add_argument("--side-yaw", type=float, default=45.0)
    ap.add_argument("--cloud", type=float, default=0.01, help="subsampled cloud fraction")
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--steps-scale", type=float, default=1.0, help="multiply every optimisation step count")
    ap.add_argument("--full", action="store_true", help="also fit the whole scans (registration + W+)")
    ap.add_argument("--no-partial", action="store_true", help="only the full-scan fits (with --full)")
    ap.add_argument("--z-starts", type=int, default=1, help="StyleGAN2: z initialisations (the paper: 1)")
    ap.add_argument("--combine", default="best", choices=("best", "mean"), help="with --z-starts > 1")
    ap.add_argument("--truncation", type=float, default=1.0, help="StyleGAN2: psi of the z step (the paper: 1)")
    ap.add_argument("--registrations", default=None, help="folder of cached partial registrations (default: OUT)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads per process")
    ap.add_argument("--workers", type=int, default=1, help="scans fitted at a time, one process each")
    args = ap.parse_args()
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    scans = sorted(p for p in Path(args.scans).iterdir() if (p / "scan.ply").is_file())[: args.limit]
    if not scans:
        raise SystemExit(f"error: no generated scans in {args.scans}")
    settings = _settings(vars(args))
    done = {s.name: _done(out / s.name, settings) for s in scans}
    todo = [s for s in scans if done[s.name] is None]
    print(f"{len(scans) - len(todo)} of {len(scans)} scans done earlier (resumed); {len(todo)} to fit", flush=True)
    if args.workers > 1 and len(todo) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        from headforge.batch.runner import cap_threads

        with ProcessPoolExecutor(min(args.workers, len(todo)), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=cap_threads, initargs=(args.threads,)) as pool:
            futures = {pool.submit(fit_scan, s, vars(args), out): s for s in todo}
            for future in as_completed(futures):
                done[futures[future].name] = _failed_scan(futures[future], future.exception()) or future.result()
    else:
        for s in todo:
            try:
                done[s.name] = fit_scan(s, vars(args), out)
            except Exception as exc:  # noqa: BLE001 -- one scan never stops a 4-hour benchmark
                done[s.name] = _failed_scan(s, exc)
    records = [r for s in scans for r in done[s.name]["records"]]
    fit_seconds = [t for s in scans for t in done[s.name]["fit_seconds"]]
    full_records = [done[s.name]["full"] for s in scans if done[s.name]["full"]]
    hair_sheet = _hair_transfer(out, scans)
    summary = _summary(records, full_records, fit_seconds)
    summary["hair_transfer_sheet"] = str(hair_sheet) if hair_sheet else None
    (out / "results.json").write_text(json.dumps({"records": records, "full": full_records, "summary": summary}, indent=1, default=float))
    (out / "table.md").write_text(_table(records, full_records))
    print(_table(records, full_records))
    print(json.dumps(summary))


SCAN_RESULT = "scan_result.json"  # a finished scan: its records, with the settings they were made with
_MODELS: dict = {}


def _failed_scan(scan_dir: Path, exc: BaseException | None) -> dict | None:
    """A scan whose observations could not be made: one error record (retried by a re-run)."""
    if exc is None:
        return None
    print(f"{scan_dir.name}: FAILED {exc}", flush=True)
    return {"records": [{"scan": scan_dir.name, "observation": "all", "error": str(exc)}], "fit_seconds": [], "full": None}


def _settings(args: dict) -> dict:
    """What a finished scan's records depend on (the StyleGAN2 fit's z starts only when not the
    paper's one, so results made before the option existed stay valid)."""
    out = {k: v for k, v in args.items() if k not in ("limit", "workers", "threads", "output", "scans", "registrations")}
    if out.get("z_starts", 1) == 1:
        out.pop("z_starts", None)
        out.pop("combine", None)
    if out.get("truncation", 1.0) == 1.0:
        out.pop("truncation", None)
    return out


REGISTRATION_KEYS = ("preset", "steps_scale", "size", "side_yaw", "cloud")  # with the partial config: what a cached registration depends on


def _registration_key(args: dict, pcfg) -> str:
    from dataclasses import asdict

    return json.dumps({**{k: args[k] for k in REGISTRATION_KEYS}, "config": asdict(pcfg)}, sort_keys=True, default=str)


def _save_registration(path: Path, key: str, reg, pm, mask, seconds: float) -> None:
    a = reg.fit.alignment
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial.npz")
    np.savez_compressed(tmp, map=pm, mask=mask, rotation=a.rotation, translation=a.translation, scale=a.scale, scale_found=a.scale_found,
                        points=reg.points_canonical, face_coverage=reg.fit.face_coverage, seconds=seconds,
                        density=reg.density, key=key,
                        **{f"param.{k}": v.detach().numpy() for k, v in a.params.items()})
    tmp.replace(path)


def _load_registration(path: Path, key: str):
    """(registration stand-in, map, mask, seconds) of a cached partial registration, or None."""
    from types import SimpleNamespace

    from headforge.craft.register import Alignment

    try:
        with np.load(path) as d:  # closed after reading: a 60-observation run opens one per observation
            if str(d["key"]) != key:
                return None
            params = {k[6:]: torch.as_tensor(d[k]) for k in d.files if k.startswith("param.")}
            align = Alignment(float(d["scale"]), float(d["scale_found" if "scale_found" in d.files else "scale"]), d["rotation"], d["translation"], params, float("nan"))
            fit = SimpleNamespace(alignment=align, face_coverage=float(d["face_coverage"]))
            reg = SimpleNamespace(fit=fit, density=str(d["density"]), points_canonical=d["points"])
            return reg, d["map"], d["mask"], float(d["seconds"])
    except (OSError, KeyError, ValueError):
        return None


def _done(folder: Path, settings: dict) -> dict | None:
    """A scan finished by an earlier run with the same settings (resume), else None."""
    try:
        data = json.loads((folder / SCAN_RESULT).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return data if data.get("settings") == settings else None


def fit_scan(scan_dir: Path, args: dict, out: Path) -> dict:
    """Every observation of one scan (and its full fit with --full): {records, fit_seconds, full},
    also written to OUT/<scan>/scan_result.json (last, so a killed scan is redone)."""
    torch.set_num_threads(args["threads"])
    opts = F.FitOptions(preset=args["preset"], steps_scale=args["steps_scale"], z_starts=args["z_starts"],
                        combine=args["combine"], truncation=args["truncation"])
    config = F.invert_config(opts)
    if not _MODELS:
        _MODELS.update({m: F.load_model(args["run"], m) for m in METHODS})
    models = _MODELS
    base = models["bare"]
    pcfg = F._partial_config(base, opts)
    faces = base.template.faces.numpy()
    records, fit_seconds = [], []
    scan, spec, gt = load_generated(scan_dir)
    obs_list = [] if args["no_partial"] else observations(scan_dir, scan, gt, out / scan_dir.name, args["size"],
                                                          args["side_yaw"], args["cloud"])
    cache = Path(args["registrations"] or out)
    key = _registration_key(args, pcfg)
    for name, obs, cam, depth in obs_list:
        cached = _load_registration(cache / scan_dir.name / name / "registration.npz", key)
        if cached is not None:
            reg, pm, mask, seconds_reg = cached
        else:
            t0 = time.perf_counter()
            try:
                reg = register_partial(base.template, obs, pcfg)
            except Exception as exc:  # a failed observation is recorded, never silently dropped
                records.append({"scan": scan_dir.name, "observation": name, "error": str(exc)})
                print(f"{scan_dir.name} {name}: FAILED {exc}", flush=True)
                continue
            pm, mask = partial_map(reg, base.duv, base.resolution)
            seconds_reg = time.perf_counter() - t0
            _save_registration(cache / scan_dir.name / name / "registration.npz", key, reg, pm, mask, seconds_reg)
        to_scan = to_scan_frame(obs, cam)
        regions = {"observed": lambda p, lab, c=cam, d=depth: visible(p, c, d),
                   "unseen": lambda p, lab, c=cam, d=depth: ~visible(p, c, d),
                   "unseen_back_hair": lambda p, lab, c=cam, d=depth: ~visible(p, c, d) & np.isin(lab, (2, 3))}
        rec = {"scan": scan_dir.name, "observation": name, "hair_style": spec["hair_style"], "variant": spec["variant"],
               "expression": bool(spec["expression"]), "points": len(obs.points), "density": reg.density,
               "observed_texels": float(mask.mean()), "face_coverage": reg.fit.face_coverage,
               "seconds_registration": seconds_reg, "methods": {}}
        meshes = {}
        for m, model in models.items():
            fr = F.fit_map(model, pm, mask, config, opts.noise, opts.seed)
            v = F.mesh_of(model, fr.map_m, reg.fit.alignment.params, pcfg.register.smooth_iterations)
            scores = F.completion_scores(to_scan(reg.fit.alignment, v), faces, scan.vertices, scan.faces, gt["labels"], regions)
            rec["methods"][m] = {"scores": scores, "seconds_latent": fr.seconds}
            meshes[m] = v
            if m == "stylegan2" and name == "front":
                _write_fit_folder(out / scan_dir.name / name / "stylegan2_fit", model, fr, reg)
        fit_seconds.append(seconds_reg + rec["methods"]["stylegan2"]["seconds_latent"])
        _picture(out / scan_dir.name / name / "picture.png", reg, meshes, faces, scan, obs, cam, base)
        (out / scan_dir.name / name / "scores.json").write_text(json.dumps(rec, indent=1))
        records.append(rec)
        line = "  ".join(f"{m} {rec['methods'][m]['scores']['unseen']['chamfer_mm']:.2f}/"
                         f"{rec['methods'][m]['scores']['observed']['chamfer_mm']:.2f}" for m in METHODS)
        print(f"{scan_dir.name} {name} ({spec['hair_style']}, {spec['variant']}): "
              f"unseen/observed Chamfer mm  {line}  ({fit_seconds[-1]:.0f} s)", flush=True)
    full = _full_fit(scan_dir, models, opts, config, out) if args["full"] else None
    result = {"settings": _settings(args), "records": records, "fit_seconds": fit_seconds, "full": full}
    (out / scan_dir.name).mkdir(parents=True, exist_ok=True)
    tmp = out / scan_dir.name / (SCAN_RESULT + ".partial")
    tmp.write_text(json.dumps(result, indent=1, default=float))
    tmp.replace(out / scan_dir.name / SCAN_RESULT)
    return json.loads(json.dumps(result, default=float))


def visible(points, cam, depth):
    return F.visible_in_depth(points, cam, depth)


def _write_fit_folder(folder: Path, model, fr, reg) -> None:
    """map.png + params.json: what transfer-hair reads."""
    from headforge.craft import uvmap

    folder.mkdir(parents=True, exist_ok=True)
    uvmap.write_map(folder / "map.png", fr.map_m)
    (folder / "params.json").write_text(json.dumps({"head_model": model.meta["head_model"], "levels": model.levels,
                                                    "params": {k: v.tolist() for k, v in reg.fit.alignment.params.items()}}))


def _picture(path: Path, reg, meshes: dict, faces, scan, obs, cam, base) -> None:
    S = 192
    target = meshes["bare"][base.template.regions["face"]].mean(0) + np.array([0.0, -0.02, -0.06])
    gt_canon = reg.fit.alignment.to_canonical(((scan.vertices @ cam.R.T + cam.t) @ obs.to_source))
    grey = lambda n: np.tile([0.75, 0.75, 0.78], (n, 1))  # noqa: E731
    rows = []
    for yaw in (20.0, 160.0):
        row = [F.point_render(reg.points_canonical, S, yaw, target)]
        row += [render_mesh(meshes[m], faces, grey(len(meshes[m])), S, yaw, target) for m in METHODS]
        row.append(render_mesh(gt_canon, scan.faces, grey(len(gt_canon)), S, yaw, target))
        rows.append(row)
    write_png(path, F.picture(rows, ["observation", *METHODS, "ground truth"]))


def _full_fit(scan_dir: Path, models: dict, opts, config, out: Path) -> dict:
    """Registration, then the whole map: fitted mesh -> scan beside registration -> scan."""
    from headforge.craft import register as reg_mod
    from headforge.craft import uvmap
    from headforge.craft.pipeline import ItemOptions, config_for, load_any

    base = models["bare"]
    item = ItemOptions(preset=opts.preset, map_size=base.resolution, steps_scale=opts.steps_scale)
    rcfg = config_for(item)
    rcfg.levels = base.levels
    scan, gt = load_any(scan_dir, item)
    reg = reg_mod.register(base.template, scan, rcfg)
    raw, mask = uvmap.bake(reg.displacement, base.duv, base.resolution)
    target_m = uvmap.postprocess_seams(raw, mask, base.duv, blend=0)
    faces = base.template.faces.numpy()
    regions = {"face": lambda p, lab: lab == 1, "hair_scalp": lambda p, lab: np.isin(lab, (2, 3))}
    params = reg.alignment.params
    rec = {"scan": scan_dir.name, "hair_style": gt["spec"]["hair_style"], "variant": gt["spec"]["variant"]}
    v = F.mesh_of(base, target_m, params, rcfg.smooth_iterations)
    rec["registration"] = F.completion_scores(v, faces, reg.scan_canonical, scan.faces, gt["labels"], regions)
    for m in ("stylegan2", "pca"):
        fr = F.fit_map(models[m], target_m, None, config, opts.noise, opts.seed)
        v = F.mesh_of(models[m], fr.map_m, params, rcfg.smooth_iterations)
        rec[m] = F.completion_scores(v, faces, reg.scan_canonical, scan.faces, gt["labels"], regions)
        rec[m]["seconds"] = fr.seconds
    print(f"full {scan_dir.name}: Chamfer mm registration {rec['registration']['all']['chamfer_mm']:.2f}, "
          f"stylegan2 {rec['stylegan2']['all']['chamfer_mm']:.2f}, pca {rec['pca']['all']['chamfer_mm']:.2f}", flush=True)
    return rec


def _hair_transfer(out: Path, scans: list[Path]) -> Path | None:
    fits = [out / s.name / "front" / "stylegan2_fit" for s in scans]
    fits = [f for f in fits if (f / "map.png").is_file()]
    if len(fits) < 2:
        return None
    sheets = []
    for a, b in ((fits[0], fits[1]), (fits[1], fits[0])):
        dest = out / f"hair_{a.parent.parent.name}_with_{b.parent.parent.name}"
        F.transfer_hair(a, b, dest, log=lambda m: None)
        sheets.append(dest / "sheet.png")
    return sheets[0]


def _mean(records, method, region, key="chamfer_mm"):
    vals = [r["methods"][method]["scores"][region][key] for r in records if "methods" in r]
    vals = [v for v in vals if np.isfinite(v)]
    return float(np.mean(vals)) if vals else float("nan")


def _summary(records, full_records, fit_seconds) -> dict:
    """The final JSON line. Without a completed observation (--no-partial, or every observation
    failed) the completion figures and verdicts are null: never NaN or a false verdict."""
    ok = [r for r in records if "methods" in r]
    s = {"n_scans": len({r["scan"] for r in records}), "n_observations": len(ok), "failed": len(records) - len(ok)}
    figure = (lambda m, region: _mean(ok, m, region)) if ok else (lambda m, region: None)  # noqa: E731
    s.update(completion_chamfer_mm=figure("stylegan2", "all"), completion_unseen_mm=figure("stylegan2", "unseen"),
             completion_observed_mm=figure("stylegan2", "observed"),
             completion_unseen_back_hair_mm=figure("stylegan2", "unseen_back_hair"))
    for m, key in (("mean", "mean_map"), ("pca", "pca"), ("bare", "bare_head")):
        s[f"{key}_unseen_mm"] = figure(m, "unseen")
        s[f"{key}_observed_mm"] = figure(m, "observed")
        s[f"{key}_chamfer_mm"] = figure(m, "all")
    s["target_unseen_beats_all"] = s["target_observed_within_10pct"] = s["fit_seconds"] = None
    if ok:
        base_unseen = min(s["mean_map_unseen_mm"], s["pca_unseen_mm"], s["bare_head_unseen_mm"])
        base_obs = min(s["mean_map_observed_mm"], s["pca_observed_mm"], s["bare_head_observed_mm"])
        s["target_unseen_beats_all"] = bool(s["completion_unseen_mm"] < base_unseen)
        s["target_observed_within_10pct"] = bool(s["completion_observed_mm"] <= 1.1 * base_obs)
        s["fit_seconds"] = float(statistics.median(fit_seconds)) if fit_seconds else None
    if full_records:
        s["n_full_scans"] = len(full_records)
        s.update({f"full_{m}_chamfer_mm": v for m, v in _full_means(full_records).items()})
        s["full_stylegan2_seconds"] = float(statistics.median([r["stylegan2"]["seconds"] for r in full_records]))
    return s


FULL_COLUMNS = ("registration", "stylegan2", "pca")


def _full_means(full_records) -> dict[str, float]:
    """Mean whole-head Chamfer (mm) of the full-scan fits, per column of FULL_COLUMNS."""
    return {m: float(np.mean([r[m]["all"]["chamfer_mm"] for r in full_records])) for m in FULL_COLUMNS}


def _table(records, full_records) -> str:
    ok = [r for r in records if "methods" in r]
    lines = []
    if ok:
        lines += _completion_table(ok)
    if full_records:
        lines += ["", "| full-scan fit, Chamfer mm | registration | stylegan2 | pca |", "| --- | --- | --- | --- |"]
        for r in full_records:
            lines.append(f"| {r['scan']} ({r['hair_style']}, {r['variant']}) | "
                         + " | ".join(f"{r[m]['all']['chamfer_mm']:.2f}" for m in FULL_COLUMNS) + " |")
        lines.append(f"| mean ({len(full_records)}) | " + " | ".join(f"{v:.2f}" for v in _full_means(full_records).values()) + " |")
    return "\n".join(lines).strip("\n") + "\n"


def _completion_table(ok) -> list[str]:
    lines = ["| completion (mean over observations), mm | " + " | ".join(METHODS) + " |",
             "| --- |" + " --- |" * len(METHODS)]
    for region in REGIONS:
        for key, label in (("chamfer_mm", "Chamfer"), ("gt_to_pred_mm", "scan -> completion")):
            lines.append(f"| {region}: {label} | " + " | ".join(f"{_mean(ok, m, region, key):.2f}" for m in METHODS) + " |")
    for field in ("observation", "hair_style", "variant"):
        lines += ["", f"| unseen Chamfer by {field.replace('_', ' ')}, mm | " + " | ".join(METHODS) + " |",
                  "| --- |" + " --- |" * len(METHODS)]
        for k in sorted({r[field] for r in ok}):
            sub = [r for r in ok if r[field] == k]
            lines.append(f"| {k} ({len(sub)}) | " + " | ".join(f"{_mean(sub, m, 'unseen'):.2f}" for m in METHODS) + " |")
    return lines


if __name__ == "__main__":
    main()
