"""HeadCraft's Tables 1-2 on held-out registrations: MMD-CD, COV-CD, 1-NNA-CD and JSD
(PointFlow's definitions, :mod:`headforge.metrics.distribution`) per model, over several
sampling seeds, and Fig. 5's memorisation check.

Reference set: the registered meshes (``registered.ply``) of a held-out map folder (part 1's
``headforge craft register`` output of scans never used for training). Each generated mesh is a
sampled map (post-processed) on an identity with a random expression and jaw drawn from the
training registrations' statistics (the paper: random FLAME shape, expression and jaw), as many
meshes as held-out scans. MMD, 1-NNA and JSD use every held-out scan; COV uses one neutral scan
per identity (B: FaceVerse's per-subject grouping).

Units: clouds in metres; Chamfer distances (sum of the two mean squared nearest-neighbour
distances) are reported in mm^2. JSD: the clouds divided by the held-out set's largest
absolute coordinate after centring (so they fit [-0.5, 0.5]^3 with margin 0.5 / 0.5), on
PointFlow's 28^3 grid.

Memorisation (Fig. 5): L2 distance over the scalp island of each sample's map to its nearest
training map, against the same for every held-out map. A model that copies training maps has
samples much closer to the training set than unseen scans are.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from headforge.craft.generative import data as D
from headforge.craft.generative import sample as S
from headforge.craft.generative import train as T
from headforge.errors import HeadforgeError
from headforge.metrics import distribution as dist


def heldout_set(folder: str | Path, meta: dict, points: int, seed: int = 0) -> dict:
    """Clouds (S, P, 3) of the held-out registered meshes, their maps at the run's resolution
    (for the memorisation check) and their head-model parameters. When ``folder`` is the run's
    own training folder, its training keys are skipped (the identities the run held out) and an
    identity on both sides is an error; any other folder is another scan set, whose keys name
    its own identities."""
    import trimesh

    from headforge.craft.register import sample_scan

    items = D.list_maps(folder)
    if Path(folder).resolve() == Path(meta["maps"]).resolve():  # the run's own folder: the identities it held out
        train_keys = set(meta["train_keys"])
        train_ids = {D.identity_of(k) for k in train_keys}
        items = [it for it in items if it.key not in train_keys]
        if not items:
            raise HeadforgeError(f"every map of {folder} was used for training: pass held-out scans (other identities)")
        shared = sorted({it.identity for it in items} & train_ids)
        if shared:
            raise HeadforgeError(f"held-out identities {shared[:3]} are also in the training set: pass other identities")
    # another folder is another scan set: its keys name its own identities (id000 of a held-out set is
    # not id000 of the training set); a scan that is in both is caught by its map (evaluate)
    clouds, neutral, keys, params = [], [], [], []
    for it in items:
        ply = it.path.parent / "registered.ply"
        if not ply.is_file():
            raise HeadforgeError(f"{it.path.parent} has no registered.ply: HELDOUT must be a headforge craft register output")
        if it.head_model and it.head_model != meta["head_model"]:
            raise HeadforgeError(f"{it.key} was registered on {it.head_model}, the run on {meta['head_model']}")
        mesh = trimesh.load(ply, process=False)
        clouds.append(sample_scan(np.asarray(mesh.vertices), np.asarray(mesh.faces), points, seed)[:points])
        neutral.append(it.key == it.identity)
        keys.append(it.key)
        params.append({k: np.asarray(v, np.float32).reshape(1, -1) for k, v in (it.params or {}).items()
                       if k in ("shape", "expression", "jaw_pose")})
    ms = D.load_maps(folder, meta["resolution"])
    maps = ms.maps[[ms.keys.index(k) for k in keys]]
    return {"clouds": np.stack(clouds), "neutral": np.asarray(neutral), "keys": keys, "maps": maps, "params": params}


def generated_clouds(model: S.Model, n: int, seed: int, points: int, truncation: float,
                     params: list[dict] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(clouds (n, P, 3), post-processed maps (n, R, R, 3)) of ``n`` generated meshes, on
    ``params`` (head-model parameters per mesh) or on sampled identities, expressions and jaws."""
    from headforge.craft.register import sample_scan

    maps = S.postprocess(S.sample_maps(model, n, truncation, seed), model.meta)
    if params is None:
        params = S.sample_identities(model.meta, n, seed, expressions=True)
    verts = S.meshes(model.meta, maps, params)
    tpl, _ = S.template(model.meta)
    faces = tpl.faces.numpy()
    clouds = np.stack([sample_scan(v, faces, points, seed * 1000 + i)[:points] for i, v in enumerate(verts)])
    return clouds, maps


def scalp_distances(maps: np.ndarray, train: np.ndarray, scalp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nearest training index, L2 distance in mm over the scalp texels) of each map."""
    a = maps[:, scalp].reshape(len(maps), -1)
    b = train[:, scalp].reshape(len(train), -1)
    d = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)) * 1000 / np.sqrt(scalp.sum())  # RMS over texels, mm
    return d.argmin(1), d.min(1)


def metrics(gen: np.ndarray, ref: np.ndarray, ref_neutral: np.ndarray, scale: float, rr: np.ndarray) -> dict:
    """The table's metrics of one generated set against the held-out set (clouds centred, metres).
    ``rr``: the held-out set's own Chamfer matrix, computed once for every model and seed."""
    m = dist.mmd_cov_1nna_from(dist.pairwise_chamfer(gen, ref), dist.pairwise_chamfer(gen), rr,
                               cov_columns=ref_neutral if ref_neutral.any() else None)
    return {"mmd": 1e6 * m["mmd_cd"], "cov": 100 * m["cov_cd"], "one_nna": 100 * m["1nna_cd"],
            "jsd": dist.jsd(gen / scale, ref / scale)}


def evaluate(run: str | Path, heldout: str | Path, methods: list[str] | None = None, seeds=(0, 1, 2), points: int = 2048,
             truncation: float = 1.0, log=print, identities: str = "sampled") -> dict:
    """Table rows {method: {metric: mean, metric_std: spread over seeds}} + memorisation.

    ``identities``: "sampled" (the paper: every generated map on an identity, expression and
    jaw drawn from the training registrations' statistics) or "heldout" (a diagnostic: the k-th
    generated map on the k-th held-out scan's own registered identity, expression and jaw, so
    the two sets differ only by their displacement maps)."""
    if identities not in ("sampled", "heldout"):
        raise HeadforgeError(f"--identities must be sampled or heldout, got {identities!r}")
    from headforge.craft.generative.data import texel_islands

    meta = T.read_run(run)
    methods = methods or list(meta["methods"]) + [S.BARE]
    if not methods:
        raise HeadforgeError(f"{run} has no trained model")
    ref = heldout_set(heldout, meta, points)
    if identities == "heldout" and not all("shape" in p for p in ref["params"]):
        raise HeadforgeError(f"--identities heldout needs the held-out registrations' params.json (shape) in {heldout}")
    fixed = ref["params"] if identities == "heldout" else None
    centre = ref["clouds"].reshape(-1, 3).mean(0)
    ref_c = ref["clouds"] - centre
    scale = 2 * float(np.abs(ref_c).max()) / 0.9  # fits [-0.45, 0.45]
    n = len(ref_c)
    train = D.from_model(T.train_maps(run))
    scalp = texel_islands(meta["head_model"], meta["levels"], meta["resolution"]) == 0
    held_idx, held_nn = scalp_distances(ref["maps"], train, scalp)
    if held_nn.min() < 1e-3:  # mm: the same registration on both sides
        k = int(held_nn.argmin())
        raise HeadforgeError(f"held-out map {ref['keys'][k]} is training map {meta['train_keys'][held_idx[k]]} of the run: "
                             "pass scans of other identities")
    rr = dist.pairwise_chamfer(ref_c)
    rows = {}
    for method in methods:
        model = S.load(run, method)
        per_seed = []
        sample_nn = []
        for s in seeds:
            clouds, maps = generated_clouds(model, n, 1000 + s, points, truncation, fixed)
            per_seed.append(metrics(clouds - centre, ref_c, ref["neutral"], scale, rr))
            if method != S.BARE:
                sample_nn.append(scalp_distances(maps, train, scalp)[1])
        row = {}
        for k in per_seed[0]:
            vals = np.array([r[k] for r in per_seed])
            row[k], row[k + "_std"] = float(vals.mean()), float(vals.std())
        if sample_nn:
            nn = np.concatenate(sample_nn)
            row["memo_sample_nn_mm"] = float(np.median(nn))
            row["memo_sample_nn_min_mm"] = float(nn.min())
            row["memo_frac_below_heldout_min"] = float((nn < held_nn.min()).mean())
        rows[method] = row
        log(f"{method:10s} " + " ".join(f"{k} {row[k]:.3g}±{row[k + '_std']:.2g}" for k in ("mmd", "cov", "one_nna", "jsd")))
    return {"rows": rows, "heldout_nn_mm": float(np.median(held_nn)), "heldout_nn_min_mm": float(held_nn.min()),
            "n_heldout": n, "n_neutral": int(ref["neutral"].sum()), "points": points, "seeds": list(seeds),
            "truncation": truncation, "identities": identities, "jsd_grid": 28, "mmd_unit": "mm^2 (Chamfer: sum of both mean squared NN distances)",
            "resolution": meta["resolution"], "n_train": len(meta["train_keys"])}


def table(result: dict) -> str:
    lines = ["| model | MMD-CD (mm²) ↓ | COV-CD (%) ↑ | 1-NNA (%) → 50 | JSD ↓ | sample→train NN (mm) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for m, r in result["rows"].items():
        memo = f"{r['memo_sample_nn_mm']:.2f} (min {r['memo_sample_nn_min_mm']:.2f})" if "memo_sample_nn_mm" in r else "–"
        lines.append(f"| {m} | {r['mmd']:.3f} ± {r['mmd_std']:.3f} | {r['cov']:.1f} ± {r['cov_std']:.1f} | "
                     f"{r['one_nna']:.1f} ± {r['one_nna_std']:.1f} | {r['jsd']:.4f} ± {r['jsd_std']:.4f} | {memo} |")
    lines.append(f"\nheld-out scan → nearest training map: median {result['heldout_nn_mm']:.2f} mm, "
                 f"min {result['heldout_nn_min_mm']:.2f} mm (scalp RMS)")
    return "\n".join(lines)


def write(result: dict, path: Path) -> None:
    T.write_json(path, result)
    path.with_suffix(".md").write_text(table(result) + "\n")
