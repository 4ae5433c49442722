"""Which of a trained NHA avatar's offsets help its Table 1 geometry, and which hurt.

    python benchmarks/offset_ablation.py SUBJECT RUN [--variants all,none,no_face,no_face_border,no_face_interior]
                                         [--rings 3] [--every 4] [--shapes learned,tracked]
                                         [--params fitted,tracked]

SUBJECT is one `headforge synth` subject folder (with gt/), RUN an NHA run folder fitted on it.
The avatar is posed at the validation GT frames with its own fitted per-frame parameters (as
`headforge fit nha` exports them) and scored by `evaluate_geometry` (the Table 1 protocol, every
``--every``-th validation GT frame) once per variant, each with a group of G's offsets set to zero
after training (geometry only; nothing is retrained):

- ``all``: the avatar as trained;
- ``none``: no offsets (the template with the learned identity shape, posed by the fitted frames);
- ``no_face``: no offsets on the template's face region (lips and eyelids included);
- ``no_face_border``: none on the face vertices within ``--rings`` edge rings of the scalp, neck
  or ears (the hairline, temples and jaw line), the rest as trained;
- ``no_face_interior``: none on the other face vertices.

``--shapes`` scores each variant with the identity shape the run learned (``learned``, the default),
with the shape the tracker gave the dataset, which training started from (``tracked``), or both.
``--params`` poses the frames with the run's own per-frame parameters (``fitted``, the default:
the validation frames' from the test-time fitting) or with the tracker's (``tracked``), or both.

Prints one line per variant and shape and, last, one JSON line with every figure. A variant that
scores better than ``all`` points at offsets that the energies grew against the ground truth.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

from headforge.avatars.engine import export_geometry
from headforge.avatars.run import load_run
from headforge.errors import HeadforgeError
from headforge.metrics.benchmark import evaluate_geometry, load_subject_gt

VARIANTS = ("all", "none", "no_face", "no_face_border", "no_face_interior")
SHAPES = ("learned", "tracked")
PARAMS = ("fitted", "tracked")
SHOWN = ("normal_error_head_deg", "normal_error_face_deg", "hausdorff_full_mm", "hausdorff_face_mm",
         "hausdorff_full_outer_mm", "head_coverage")


def face_border(avatar, rings: int) -> torch.Tensor:
    """(V,) bool: face-region vertices within ``rings`` edge rings of a scalp, neck or ear vertex."""
    faces = avatar.head.faces
    reach = torch.zeros(avatar.head.num_vertices, dtype=torch.bool)
    for name in ("scalp", "neck", "ears"):
        if name in avatar.head.region_names:
            reach[avatar.head.region(name)] = True
    for _ in range(rings):
        grown = reach.clone()
        grown[faces[reach[faces].any(1)].reshape(-1)] = True
        reach = grown
    return (avatar.face_vertices > 0) & reach


def tracked_shape(run: Path, avatar) -> torch.Tensor:
    """(1, n_shape) identity shape of the run's dataset as the tracker left it (training's start)."""
    return tracked_params(run)["shape"].float()[:, : avatar.shape.shape[1]]


def tracked_params(run: Path) -> dict[str, torch.Tensor]:
    """The per-frame parameters the tracker gave the run's dataset (the run's own copy of them)."""
    from headforge.avatars.run import RunAssets

    return RunAssets.load(run).tracking


def zeroed_vertices(avatar, variant: str, rings: int) -> torch.Tensor:
    """(V,) bool: the vertices whose offsets ``variant`` sets to zero."""
    V = avatar.head.num_vertices
    face = avatar.face_vertices > 0
    if variant == "all":
        return torch.zeros(V, dtype=torch.bool)
    if variant == "none":
        return torch.ones(V, dtype=torch.bool)
    if variant == "no_face":
        return face
    border = face_border(avatar, rings)
    return border if variant == "no_face_border" else face & ~border


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("subject", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--rings", type=int, default=3)
    parser.add_argument("--every", type=int, default=4)
    parser.add_argument("--shapes", default="learned")
    parser.add_argument("--params", default="fitted")
    args = parser.parse_args()
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    shapes = [v.strip() for v in args.shapes.split(",") if v.strip()]
    param_sets = [v.strip() for v in args.params.split(",") if v.strip()]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise SystemExit(f"error: unknown variants {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")
    if not shapes or set(shapes) - set(SHAPES):
        raise SystemExit(f"error: --shapes takes {' and/or '.join(SHAPES)}, got {args.shapes!r}")
    if not param_sets or set(param_sets) - set(PARAMS):
        raise SystemExit(f"error: --params takes {' and/or '.join(PARAMS)}, got {args.params!r}")
    try:
        load_subject_gt(args.subject)
        avatar = load_run(args.run).avatar
    except HeadforgeError as err:
        raise SystemExit(f"error: {err}") from None
    avatar.eval()
    trained_offsets = avatar.offsets
    identity = {"learned": avatar.shape.detach().clone(), "tracked": tracked_shape(args.run, avatar)}
    results = {}
    fitted = {k: v.detach().clone() for k, v in avatar.frames.items()}
    tracked = avatar.params_from_tracking(tracked_params(args.run))
    frame_sets = {"fitted": fitted, "tracked": {k: tracked[k][: len(v)] for k, v in fitted.items()}}
    with tempfile.TemporaryDirectory() as tmp, torch.no_grad():
        for params in param_sets:
            for k, v in avatar.frames.items():
                v.copy_(frame_sets[params][k])
            for shape in shapes:
                avatar.shape.data.copy_(identity[shape])
                for variant in variants:
                    zero = zeroed_vertices(avatar, variant, args.rings)
                    keep = (~zero)[:, None].float()
                    avatar.offsets = lambda neck_pose, keep=keep: trained_offsets(neck_pose) * keep
                    name = "/".join([variant] + ([shape] if shapes != ["learned"] else [])
                                    + ([f"{params} params"] if param_sets != ["fitted"] else []))
                    folder = Path(tmp) / name.replace("/", "_").replace(" ", "_")
                    folder.mkdir()
                    export_geometry(avatar, args.subject, folder / "geometry.safetensors")
                    mean = evaluate_geometry(folder, args.subject, every=args.every)["mean"]
                    results[name] = {"zeroed_vertices": int(zero.sum())} | {k: round(float(mean[k]), 3) for k in SHOWN}
                    print(f"{name:40s} zeroed {int(zero.sum()):5d} | "
                          + "  ".join(f"{k} {results[name][k]}" for k in SHOWN), flush=True)
    print(json.dumps({"subject": str(args.subject), "run": str(args.run), "every": args.every, "rings": args.rings,
                      "variants": results}))


if __name__ == "__main__":
    main()
