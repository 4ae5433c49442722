"""Where a reconstruction's geometry error is, per template region, against a synthetic subject.

    python benchmarks/geometry_regions.py SUBJECT RUN [--frames 4]

SUBJECT is one `headforge synth` subject folder (with gt/), RUN an NHA run folder fitted on it
(with geometry.safetensors from its test-time fitting). For ``--frames`` evenly spaced GT frames
of the validation split, both the tracked head model and the NHA avatar are rigidly aligned to the
GT face exactly as Table 1 aligns them (`headforge.metrics.benchmark`), then every vertex of the
full head (neck excluded) is assigned to its template region (the scalp split by position into
top-back, back and the rest; on the open-head template the whole scalp region lies behind the
head's centroid, so the rest is empty) and measured against the GT mesh:

- ``mm``: distance to the whole GT mesh (Table 1's one-sided distance, per vertex, not per area);
- ``hair_mm`` / ``skin_mm``: signed distance to the GT hair and to the GT non-hair surface,
  positive outside (along the GT face normal of the closest point);
- ``outer_mm``: distance to the GT's outer surface only (Table 1's ``hausdorff_full_outer_mm``
  per vertex: without the scalp under the hair and the hair volume's inner shell).

Prints a table (tracked → NHA per region) and, last, one JSON line with every figure.
A surface that ends inside a hair shell shows ``skin_mm > 0`` and ``hair_mm < 0``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import trimesh

from headforge.avatars.nha.model import build_template, scalp_top_back
from headforge.avatars.run import load_run
from headforge.errors import HeadforgeError
from headforge.head import load_data
from headforge.metrics.benchmark import (align_face, exported_geometry, load_subject_gt, outer_surface_faces,
                                         prediction_rows, tracked_geometry)


def region_labels(regions: dict[str, np.ndarray], rest: np.ndarray) -> np.ndarray:
    """(V,) region name per template vertex; the scalp split by rest-pose position (metres, +y up,
    +z forward): top-back = above the centroid by 6 cm and behind it, back = behind by 3 cm."""
    V = len(rest)
    labels = np.array(["other"] * V, dtype=object)
    for name, idx in regions.items():
        idx = np.asarray(idx)
        labels[idx[idx < V]] = name
    centre = rest.mean(0)
    scalp = labels == "scalp"
    top_back = scalp_top_back(rest, scalp)
    labels[top_back] = "scalp_top_back"
    labels[scalp & ~top_back & (rest[:, 2] <= centre[2] - 0.03)] = "scalp_back"  # behind by 3 cm, lower
    return labels


def signed_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    closest, distance, triangle = trimesh.proximity.closest_point(mesh, points)
    side = np.sign(((points - closest) * mesh.face_normals[triangle]).sum(1))
    return side * distance


def main() -> None:
    try:
        report()
    except HeadforgeError as err:  # a wrong subject or run folder: one line, no traceback
        raise SystemExit(f"error: {err}") from None


def report() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("subject", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--frames", type=int, default=4)
    args = parser.parse_args()

    if args.frames < 1:
        raise HeadforgeError(f"--frames must be >= 1, got {args.frames}")
    gt, info = load_subject_gt(args.subject)
    val_rows = np.nonzero(gt["frames"] >= info["train_frames"])[0]
    if len(val_rows) == 0:
        raise HeadforgeError(f"{args.subject} has no ground-truth frames in its validation split")
    rows = val_rows[np.linspace(0, len(val_rows) - 1, args.frames).round().astype(int)]
    frames = gt["frames"][rows]
    hair_label, face_label = info["labels"]["hair"], info["labels"]["face"]
    gl = gt["labels"]

    config = load_run(args.run).config
    base = load_data("open-head", None)
    nha_template = build_template(base, config.subdivide, config.remove_lower_neck)
    predictions = {
        "tracked": (tracked_geometry(args.subject, frames),
                    region_labels(base.regions, np.asarray(base.v_template))),
        "nha": (exported_geometry(args.run),
                region_labels(nha_template.regions, np.asarray(nha_template.v_template))),
    }
    gf = gt["faces"]
    hair_faces = (gl[gf] == hair_label).all(1)
    outer = outer_surface_faces(gt["vertices"][rows[0]], gf, gl, hair_label)
    gt_meshes = [(gt["vertices"][row], trimesh.Trimesh(gt["vertices"][row], gf, process=False),
                  trimesh.Trimesh(gt["vertices"][row], gf[hair_faces], process=False),
                  trimesh.Trimesh(gt["vertices"][row], gf[~hair_faces], process=False),
                  trimesh.Trimesh(gt["vertices"][row], gf[outer], process=False)) for row in rows]
    figures: dict[str, dict[str, dict[str, float]]] = {}
    for method, (pred, labels) in predictions.items():
        pred_rows = prediction_rows(pred, frames, pred.source)
        face_faces = pred.faces[pred.face_vertices[pred.faces].all(1)]
        sel = np.nonzero(pred.head_vertices)[0]
        per_region: dict[str, list[np.ndarray]] = {}
        for i, (gv, whole, hair, skin, outer_mesh) in zip(pred_rows, gt_meshes):
            aligned = align_face(pred.vertices[i], face_faces, gv, gf, gl == face_label)
            points = aligned[sel]
            d = np.stack([trimesh.proximity.closest_point(whole, points)[1],
                          signed_distance(hair, points), signed_distance(skin, points),
                          trimesh.proximity.closest_point(outer_mesh, points)[1]], 1)
            for region in np.unique(labels[sel]):
                per_region.setdefault(region, []).append(d[labels[sel] == region])
        figures[method] = {}
        for region, parts in per_region.items():
            d = np.concatenate(parts)
            figures[method][region] = {"vertices": len(d) // len(rows), "mm": 1000 * float(d[:, 0].mean()),
                                       "hair_mm": 1000 * float(d[:, 1].mean()),
                                       "skin_mm": 1000 * float(d[:, 2].mean()),
                                       "inside_hair": float((d[:, 1] < 0).mean()),
                                       "outer_mm": 1000 * float(d[:, 3].mean())}
    print(f"{'region':16s} {'verts':>6s} | {'mm':>14s} | {'hair_mm (signed)':>16s} | {'skin_mm (signed)':>16s} | "
          f"{'outer_mm':>14s}")
    print(f"{'':16s} {'(nha)':>6s} | {'tracked → nha':>14s} | {'tracked → nha':>16s} | {'tracked → nha':>16s} | "
          f"{'tracked → nha':>14s}")
    for region in sorted(figures["nha"]):
        n = figures["nha"][region]
        t = figures["tracked"].get(region)
        cell = lambda key: f"{t[key]:6.2f} → {n[key]:6.2f}" if t else f"{'':6s}   {n[key]:6.2f}"  # noqa: E731
        print(f"{region:16s} {n['vertices']:6d} | {cell('mm'):>14s} | {cell('hair_mm'):>16s} | {cell('skin_mm'):>16s} | "
              f"{cell('outer_mm'):>14s}")
    print(json.dumps({"subject": str(args.subject), "run": str(args.run), "frames": [int(f) for f in frames],
                      "regions": figures}))


if __name__ == "__main__":
    main()
