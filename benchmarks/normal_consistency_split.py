"""Where a point avatar's normal consistency is lost: by GT label, by visibility, by distance.

    python benchmarks/normal_consistency_split.py RUN SUBJECT [--every 4] [--split train --checkpoint]

RUN is a point-avatar run folder (its ``geometry.safetensors``: the posed points at the subject's
GT frames, as ``headforge eval`` scores them), SUBJECT the ``headforge synth`` subject it was
trained on. ``--checkpoint`` poses the run's last checkpoint instead (a run stopped after training,
before its held-out frames are fitted; use it with ``--split train``, whose frames are trained).
Per scored frame the points are selected and aligned exactly as the protocol's normal consistency
(:func:`headforge.metrics.benchmark.evaluate_geometry`: the same random head points, at most 4000,
after the rigid ICP of the face points to the GT face); each point's ``|cos|`` against the normal
of its closest GT surface point is then split by that point's GT label, by whether the point is
visible from the frame's camera (within ``--depth-tolerance`` mm of the nearest point splatted on
its pixel), by its distance to the GT surface and by how squarely that GT surface faces the camera
(|n . v|: 1 facing it, 0 seen edge-on). ``splatted`` replaces each visible point's own
normal by the composited normal map at its pixel (what the normal-map losses see). Prints a table,
then one JSON line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import trimesh

from headforge.errors import HeadforgeError
from headforge.metrics.benchmark import (_point_distances, exported_geometry, gt_point_labels, load_subject_gt,
                                         outer_surface_faces, prediction_rows, seen_gt_samples, split_rows,
                                         splat_normals)
from headforge.render.camera import project_points

DISTANCE_BINS_MM = (0.0, 1.0, 3.0, 10.0, np.inf)
FACING_BINS = (0.0, 0.3, 0.6, 0.8, 1.01)


def frame_split(points, normals, radius, gv, gf, gt_labels, K, res, tolerance_m):
    """Per point (P,): |cos| against the closest GT face normal, GT label, distance (m), visible
    (bool), |cos| of the splatted normal at its pixel (nan where not visible), and how squarely the
    closest GT face faces the camera (|n . view direction|)."""
    closest, distance, tri, label = gt_point_labels(points, gv, gf, gt_labels)
    gt_n = trimesh.Trimesh(gv, gf, process=False).face_normals[tri]
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True).clip(min=1e-12)
    cos = np.abs((n * gt_n).sum(1))
    facing = np.abs((gt_n * points / np.linalg.norm(points, axis=1, keepdims=True)).sum(1))
    uv = project_points(torch.from_numpy(points), torch.from_numpy(K)).numpy()
    px = np.clip(np.round(uv).astype(int), 0, res - 1)
    flat = px[:, 1] * res + px[:, 0]
    zbuf = np.full(res * res, np.inf)
    np.minimum.at(zbuf, flat, points[:, 2])
    visible = points[:, 2] <= zbuf[flat] + tolerance_m
    nmap = splat_normals(points, normals, radius, K, res).reshape(-1, 3)
    splat_cos = np.where(visible & (np.linalg.norm(nmap[flat], axis=1) > 0.5),
                         np.abs((nmap[flat] * gt_n).sum(1)), np.nan)
    return cos, label, distance, visible, splat_cos, facing


def checkpoint_geometry(run: Path, subject: Path):
    """The posed geometry of ``run``'s checkpoint at ``subject``'s GT frames (as read back from
    the geometry file :func:`export_geometry` writes, in a folder removed afterwards)."""
    import tempfile

    from headforge.avatars.engine import export_geometry
    from headforge.avatars.run import load_run

    avatar = load_run(run, "cpu", method="pointavatar").avatar
    with tempfile.TemporaryDirectory(prefix="nc_split_") as folder, torch.no_grad():
        export_geometry(avatar, subject, Path(folder) / "geometry.safetensors")
        return exported_geometry(folder)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("subject", type=Path)
    parser.add_argument("--every", type=int, default=4)
    parser.add_argument("--split", default="val", choices=("val", "train"))
    parser.add_argument("--checkpoint", action="store_true", help="pose the run's checkpoint, not its geometry file")
    parser.add_argument("--samples", type=int, default=10_000, help="as headforge eval's --samples")
    parser.add_argument("--depth-tolerance", type=float, default=5.0, help="mm behind the front point still visible")
    args = parser.parse_args()
    try:
        gt, info = load_subject_gt(args.subject)
        rows, _ = split_rows(gt, info, args.subject, args.split, args.every)
        frames = gt["frames"][rows]
        pred = checkpoint_geometry(args.run, args.subject) if args.checkpoint else exported_geometry(args.run)
        if not pred.is_points:
            raise HeadforgeError(f"{args.run} holds a mesh: this split is for point sets")
        lookup = prediction_rows(pred, frames, args.run)
    except HeadforgeError as err:
        raise SystemExit(f"error: {err}") from None
    K, res = np.asarray(info["intrinsics"]), int(info["resolution"])
    labels_face, head_labels = info["labels"]["face"], np.array(info["head_labels"])
    names = {v: k for k, v in info["labels"].items()}
    subset = np.random.default_rng(0).permutation(pred.vertices.shape[1])[:args.samples]
    outer = outer_surface_faces(gt["vertices"][rows[0]], gt["faces"], gt["labels"], info["labels"]["hair"])
    skin = np.isin(gt["labels"], head_labels) & (gt["labels"] != info["labels"]["hair"])
    gt_head_faces = np.isin(gt["labels"], head_labels)[gt["faces"]].all(1)
    pooled = {k: [] for k in ("cos", "label", "distance", "visible", "splat_cos", "facing")}
    protocol = []
    for row, f, i in zip(rows, frames, lookup):
        gv, gf = gt["vertices"][row], gt["faces"]
        regions = None if pred.face_vertices is None else (pred.face_vertices, pred.head_vertices)
        seen = seen_gt_samples(gv, gf, gt_head_faces, K, res)
        scores, aligned, aligned_n = _point_distances(pred.vertices[i], pred.normals[i], subset, gv, gf, gt["labels"],
                                                      head_labels, labels_face, outer, skin, int(f), seen, regions)
        protocol.append(scores["normal_consistency"])
        head = regions[1][subset] if regions is not None else np.ones(len(subset), bool)
        ids = subset[head][:4000]
        # visibility and the splatted map from every aligned point, scored on the protocol's points
        split = frame_split(aligned[ids], aligned_n[ids], pred.radius[i][ids], gv, gf, gt["labels"], K, res,
                            args.depth_tolerance / 1000)
        for key, value in zip(pooled, split):
            pooled[key].append(value)
    p = {k: np.concatenate(v) for k, v in pooled.items()}
    result = {"run": str(args.run), "subject": str(args.subject), "frames": len(protocol),
              "protocol_nc": float(np.mean(protocol)), "one_sided_nc": float(p["cos"].mean()), "groups": {}}
    print(f"{args.run}: protocol NC {result['protocol_nc']:.4f}, one-sided point->GT {result['one_sided_nc']:.4f} "
          f"over {len(p['cos'])} point-frames")
    groups = {f"label {names.get(int(v), v)}": p["label"] == v for v in np.unique(p["label"])}
    groups |= {"visible": p["visible"], "hidden": ~p["visible"]}
    for lo, hi in zip(DISTANCE_BINS_MM[:-1], DISTANCE_BINS_MM[1:]):
        groups[f"distance {lo:g}-{hi:g} mm"] = (p["distance"] * 1000 >= lo) & (p["distance"] * 1000 < hi)
    for lo, hi in zip(FACING_BINS[:-1], FACING_BINS[1:]):
        groups[f"facing |n.v| {lo:g}-{min(hi, 1):g}"] = (p["facing"] >= lo) & (p["facing"] < hi)
    print(f"{'group':24s} {'share':>6s} {'NC':>6s}  {'NC splatted (visible)':>22s}")
    for name, sel in groups.items():
        if not sel.any():
            continue
        sc = p["splat_cos"][sel]
        row = {"share": float(sel.mean()), "nc": float(p["cos"][sel].mean()),
               "nc_splatted": float(np.nanmean(sc)) if np.isfinite(sc).any() else None}
        result["groups"][name] = row
        splatted = f"{row['nc_splatted']:.4f}" if row["nc_splatted"] is not None else "-"
        print(f"{name:24s} {row['share']:6.3f} {row['nc']:6.4f}  {splatted:>22s}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
