"""Where a prediction's face is too deep or too shallow: depth offsets against the GT by how far behind the face's front.

    python benchmarks/face_depth_profile.py PRED SUBJECT [--every 8]

PRED is a geometry folder (``geometry.safetensors``: a point avatar's or a mesh avatar's export)
or a tracked dataset (its head model), SUBJECT the ``headforge synth`` subject. Per scored frame
the prediction's face (its own face region: a point set's ``face_points`` and ``head_points``, a
mesh's face vertices) is moved by the protocol's rigid face alignment
(:func:`headforge.metrics.benchmark._icp_to_face`), its front layer kept (within 3 mm of the
nearest prediction point on its pixel) on the GT face's pixels, and each kept point's depth
compared with the GT z-buffer at its pixel (+: behind the GT). The offsets are binned by how far
behind the GT face's frontmost pixel the GT surface lies: the front of the face (nose, forehead)
in the first bins, its sides (cheeks towards the ears, seen at grazing angles in a frontal clip)
in the last. A uniform scale error shows as offsets that grow with the bin; the splats' outline
spill of a point avatar as sides too deep. Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.metrics.benchmark import (_face_samples, _face_subset, _icp_to_face, _moved, load_prediction,
                                         load_subject_gt, prediction_rows, split_rows)
from headforge.render import mesh
from headforge.render.camera import Cameras, project_points

BINS_MM = (0, 10, 20, 30, 45, 60, 200)
FRONT_LAYER_M = 3e-3


def face_samples(pred, row: int) -> np.ndarray:
    """(S, 3) camera-space samples of the prediction's face: its face points, or 5000 area samples
    of its face triangles."""
    if pred.is_points:
        face = pred.face_vertices & pred.head_vertices
        return np.asarray(pred.vertices[row][face], np.float64)
    return _face_samples(pred.vertices[row], pred.faces[pred.face_vertices[pred.faces].all(1)])


def frame_offsets(samples: np.ndarray, gv: np.ndarray, gf: np.ndarray, face_label_faces: np.ndarray,
                  gt_face_vertices: np.ndarray, cams: Cameras, K: np.ndarray, res: int) -> tuple[np.ndarray, np.ndarray]:
    """(depth offset (m), GT depth behind the face's front (m)) of the aligned front-layer samples."""
    aligned = _moved(samples, _icp_to_face(_face_subset(samples), gv, gf, gt_face_vertices, centre=True))
    frags = mesh.rasterize(cams, torch.from_numpy(gv.astype(np.float32))[None], torch.from_numpy(gf.astype(np.int64)))
    zbuf, face_id = frags.depth[0].numpy(), frags.face_id[0].numpy()
    face_px = np.isin(face_id, face_label_faces)
    front_z = zbuf[face_px].min()
    px = np.clip(np.round(project_points(torch.from_numpy(aligned.astype(np.float32)), torch.from_numpy(K)).numpy()),
                 0, res - 1).astype(int)
    flat = px[:, 1] * res + px[:, 0]
    nearest = np.full(res * res, np.inf)
    np.minimum.at(nearest, flat, aligned[:, 2])
    keep = face_px[px[:, 1], px[:, 0]] & (aligned[:, 2] <= nearest[flat] + FRONT_LAYER_M)
    gt_z = zbuf[px[keep, 1], px[keep, 0]]
    return aligned[keep, 2] - gt_z, gt_z - front_z


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pred", type=Path)
    parser.add_argument("subject", type=Path)
    parser.add_argument("--every", type=int, default=8)
    args = parser.parse_args()
    try:
        gt, info = load_subject_gt(args.subject)
        rows, _ = split_rows(gt, info, args.subject, "val", args.every)
        frames = gt["frames"][rows]
        pred = load_prediction(args.pred, frames)
        lookup = prediction_rows(pred, frames, args.pred)
        if pred.face_vertices is None:
            raise HeadforgeError(f"{args.pred} carries no face region of its own (face_points)")
    except HeadforgeError as err:
        raise SystemExit(f"error: {err}") from None
    K, res = np.asarray(info["intrinsics"]), int(info["resolution"])
    cams = Cameras.at_origin(torch.from_numpy(K.astype(np.float32)), 1, res)
    gt_face = gt["labels"] == info["labels"]["face"]
    face_label_faces = np.nonzero(gt_face[gt["faces"]].all(1))[0]
    bins = np.asarray(BINS_MM) * 1e-3
    pooled = [[] for _ in range(len(bins) - 1)]
    for row, i in zip(rows, lookup):
        dz, behind = frame_offsets(face_samples(pred, i), gt["vertices"][row], gt["faces"], face_label_faces, gt_face,
                                   cams, K, res)
        which = np.digitize(behind, bins) - 1
        for b in range(len(pooled)):
            pooled[b].extend(dz[which == b])
    print(f"{args.pred} against {args.subject}: {len(rows)} held-out frames; depth offset of the front face layer "
          "after the rigid face alignment (mm, + behind the GT)")
    print("| GT surface behind the face's front (mm) | points | median offset (mm) |")
    print("| --- | --- | --- |")
    summary = {}
    for b, values in enumerate(pooled):
        name = f"{BINS_MM[b]}-{BINS_MM[b + 1]}"
        median = float(np.median(values) * 1e3) if values else float("nan")
        print(f"| {name} | {len(values)} | {median:+.2f} |")
        summary[f"offset_{name}_mm"] = round(median, 2)
    print(json.dumps({"pred": str(args.pred), "subject": str(args.subject), "frames": len(rows), **summary}))


if __name__ == "__main__":
    main()
