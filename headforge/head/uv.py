"""UV layouts of a head model beyond the one it ships with.

:func:`craft_layout` -- HeadCraft's layout (Fig. 4/12): the seam runs around the face border, so
face and scalp are separate islands; scalp (with neck, ears and the inner parts) on the left,
face on the right, scaled to the same texel density. Face and scalp are one chart each
(Tutte embeddings: the face border on a circle, for both islands; holes closed by virtual fans,
so no triangle flips); the closed inner parts (eyeballs, eye and mouth cavities) go to a
small ``xatlas`` atlas below the face. The layout is cached next to the head model.

UVs: [0, 1]^2, v up (HeadModelData's convention); per face corner through ``uv_faces``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError
from headforge.head.model import HeadModelData

LAYOUT_VERSION = 1
ISLAND_GAP = 0.02  # UV distance kept free between the two islands


@dataclass
class UVLayout:
    uvs: np.ndarray  # (T, 2)
    uv_faces: np.ndarray  # (F, 3) into uvs, same face order as the model's faces
    island: np.ndarray  # (F,) 0 = scalp (with neck, ears), 1 = face, 2 = inner parts
    uv_vertex: np.ndarray  # (T,) geometry vertex of each uv coordinate
    meta: dict

    def save(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".partial.npz")
        np.savez(tmp, uvs=self.uvs, uv_faces=self.uv_faces, island=self.island, uv_vertex=self.uv_vertex,
                 meta=np.array(repr(self.meta)))
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> UVLayout:
        import ast

        z = np.load(path)
        return cls(z["uvs"], z["uv_faces"], z["island"], z["uv_vertex"], ast.literal_eval(str(z["meta"])))


def face_island(data: HeadModelData) -> np.ndarray:
    """(F,) bool: triangles of the face island (at least two corners in the 'face' region)."""
    if "face" not in data.regions:
        raise HeadforgeError(f"head model {data.name!r} has no 'face' region for the HeadCraft layout")
    inside = np.zeros(len(data.v_template), bool)
    inside[data.regions["face"]] = True
    return inside[data.faces].sum(1) >= 2


def _atlas(vertices: np.ndarray, faces: np.ndarray, resolution: int):
    """xatlas charts + packing of a (small) mesh: (vertex of each uv, uv faces, uvs in [0,1], charts)."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = resolution
    pack.padding = 2
    atlas.generate(xatlas.ChartOptions(), pack)
    vmapping, indices, uvs = atlas[0]
    return np.asarray(vmapping, np.int64), np.asarray(indices, np.int64), np.asarray(uvs, np.float64), int(atlas.chart_count)


def _area(v, f):
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()


def _uv_area(uv, f):
    e1, e2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _submesh(v, f):
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    return used, v[used], remap[f]


def _circle(v: np.ndarray, loop: np.ndarray, radius: float, start: np.ndarray | None = None) -> np.ndarray:
    """Positions of a boundary loop on a circle, spaced by arc length; the loop vertex nearest
    ``start`` (a 3D point) at angle -90 deg (the bottom), running counter-clockwise."""
    seg = np.linalg.norm(v[np.roll(loop, -1)] - v[loop], axis=1)
    s = np.r_[0.0, np.cumsum(seg)[:-1]] / seg.sum()
    k = 0 if start is None else int(np.argmin(np.linalg.norm(v[loop] - start, axis=1)))
    s = (s - s[k]) % 1.0
    angle = -0.5 * np.pi + 2 * np.pi * s
    return radius * np.stack([np.cos(angle), np.sin(angle)], 1)


def _oriented(v, f, loop):
    """Make a boundary loop run counter-clockwise when seen from outside (face orientation)."""
    edges = {(int(a), int(b)) for a, b in np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])}
    return loop if (int(loop[0]), int(loop[1])) in edges else loop[::-1]


def _harmonic(v: np.ndarray, f: np.ndarray, b: np.ndarray, bc: np.ndarray, weights: str = "uniform") -> np.ndarray:
    """Harmonic map with fixed boundary values. ``uniform`` (Tutte's barycentric embedding, no
    flips for a convex boundary) or ``cotan`` (libigl's, closer to conformal, may flip)."""
    if weights == "cotan":
        import igl

        return igl.harmonic(v, f.astype(np.int64), b.astype(np.int64), bc, 1)
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n = len(v)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    A.data[:] = 1.0
    L = sp.diags(np.asarray(A.sum(1)).ravel()) - A
    free = np.setdiff1d(np.arange(n), b)
    out = np.zeros((n, 2))
    out[b] = bc
    rhs = -L[free][:, b] @ bc
    out[free] = np.stack([spsolve(L[free][:, free].tocsc(), rhs[:, k]) for k in range(2)], 1)
    return out


def parametrize_disk(v: np.ndarray, f: np.ndarray, loop: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Harmonic map (libigl, cotangent weights) of a disk-like mesh with its ``loop`` fixed on
    the unit circle; other boundaries (eye and mouth holes) stay free."""
    import igl

    loop = _oriented(v, f, loop)
    # close the other holes with a fan around a virtual centre: every vertex is then interior and
    # Tutte's theorem (convex boundary) gives an embedding without flips
    extra_v, extra_f = [v], [f]
    n = len(v)
    for hole in igl.boundary_loop_all(f.astype(np.int64)):
        hole = np.asarray(hole)
        if len(hole) == len(loop) and set(hole.tolist()) == set(loop.tolist()):
            continue
        hole = _oriented(v, f, hole)
        extra_v.append(v[hole].mean(0, keepdims=True))
        extra_f.append(np.stack([np.roll(hole, -1), hole, np.full(len(hole), n)], 1))
        n += 1
    vv, ff = np.concatenate(extra_v), np.concatenate(extra_f)
    return _harmonic(vv, ff, loop, _circle(v, loop, 1.0, start))[:len(v)]


def build_craft_layout(data: HeadModelData) -> UVLayout:
    """Build the layout (see the module doc). The face island is a disk (harmonic map, its
    border on a circle); the scalp island (scalp, neck, ears) is the same with the face border
    on its circle and the neck cut closed (a virtual fan), so the neck end lies in the middle;
    both circles start at the chin so the seam's two sides run alike. The closed inner parts (eyeballs, eye and mouth cavities; frozen
    in registration, displacement 0) share a small xatlas atlas."""
    import igl
    import trimesh

    is_face = face_island(data)
    v, F = data.v_template, data.faces
    scalp_f = np.nonzero(~is_face)[0]
    comp = trimesh.graph.connected_component_labels(trimesh.Trimesh(v, F[scalp_f], process=False).face_adjacency,
                                                    node_count=len(scalp_f))
    main = np.bincount(comp).argmax()
    groups = {"scalp": scalp_f[comp == main], "face": np.nonzero(is_face)[0], "inner": scalp_f[comp != main]}
    chin = v[data.regions["face"]][np.argmin(v[data.regions["face"], 1])]
    charts = {}
    # face: the outer loop is the longest boundary
    used, sv, sf = _submesh(v, F[groups["face"]])
    loops = sorted(igl.boundary_loop_all(sf.astype(np.int64)), key=len)
    uv_face = parametrize_disk(sv, sf, np.asarray(loops[-1]), chin)
    charts["face"] = (used, sf, uv_face)
    used_s, sv, sf = _submesh(v, F[groups["scalp"]])
    loops = [np.asarray(lp) for lp in igl.boundary_loop_all(sf.astype(np.int64))]
    # outer = the loop shared with the face island, inner = the neck cut (lowest loop)
    face_verts = set(np.unique(F[groups["face"]]).tolist())
    shared = [np.mean([int(used_s[i]) in face_verts for i in lp]) for lp in loops]
    outer = loops[int(np.argmax(shared))]
    rest = [lp for k, lp in enumerate(loops) if k != int(np.argmax(shared))]
    if len(rest) != 1:
        raise HeadforgeError(f"the scalp island of {data.name!r} must be an annulus (face border + neck cut), "
                             f"it has {len(loops)} boundary loops")
    uv_scalp = parametrize_disk(sv, sf, outer, chin)  # the neck cut is closed by a virtual fan: no flips
    charts["scalp"] = (used_s, sf, uv_scalp)
    used, sv, sf = _submesh(v, F[groups["inner"]])
    vmap, idx, uv, n_inner = _atlas(sv, sf, 256)
    charts["inner"] = (used[vmap], idx, uv)
    # Equal texel density: disk radii with R^2 * uv_area_at_unit_radius / surface_area equal.
    a_s, a_f = _area(v, F[groups["scalp"]]), _area(v, F[groups["face"]])
    u_s, u_f = abs(_uv_area(uv_scalp, charts["scalp"][1]).sum()), abs(_uv_area(uv_face, charts["face"][1]).sum())
    ratio = np.sqrt((a_f / u_f) / (a_s / u_s))  # R_face / R_scalp
    gap = ISLAND_GAP
    r_s = (1.0 - 3 * gap) / (2 + 2 * ratio)
    r_f = ratio * r_s
    inner_side = min(1.0 - 3 * gap - 2 * r_f, 2 * r_f, 0.2)
    place = {"scalp": (np.array([gap + r_s, 0.5]), r_s), "face": (np.array([1 - gap - r_f, 1 - gap - r_f]), r_f)}
    uvs, uv_faces, uv_vertex, island = [], np.zeros_like(F), [], np.zeros(len(F), np.int8)
    count = 0
    for code, name in enumerate(("scalp", "face", "inner")):
        vert, f, uv = charts[name]
        if name == "inner":
            uv = uv * inner_side + np.array([1 - gap - 2 * r_f, gap])
        else:
            centre, radius = place[name]
            uv = uv * radius + centre
        uvs.append(uv)
        uv_faces[groups[name]] = f + count
        uv_vertex.append(vert)
        island[groups[name]] = code
        count += len(uv)
    uvs = np.concatenate(uvs)
    uv_vertex = np.concatenate(uv_vertex)
    stats = {}
    for code, name in enumerate(("scalp", "face")):
        fs = np.nonzero(island == code)[0]
        signed = _uv_area(uvs, uv_faces[fs])
        a3 = 0.5 * np.linalg.norm(np.cross(v[F[fs, 1]] - v[F[fs, 0]], v[F[fs, 2]] - v[F[fs, 0]]), axis=1)
        stretch = np.abs(signed) / np.maximum(a3, 1e-12)
        stats[name] = {"uv_per_metre": float(np.sqrt(np.abs(signed).sum() / a3.sum())),
                       "area_stretch_p5_p95": [float(np.percentile(stretch, 5) / np.median(stretch)),
                                               float(np.percentile(stretch, 95) / np.median(stretch))],
                       "flipped": int((signed <= 0).sum())}
    meta = {"version": LAYOUT_VERSION, "model": data.name, "inner_charts": n_inner, "islands": stats,
            "density_ratio_face_to_scalp": stats["face"]["uv_per_metre"] / stats["scalp"]["uv_per_metre"],
            "uv_coverage": float(np.abs(_uv_area(uvs, uv_faces)).sum())}
    return UVLayout(uvs, uv_faces, island, uv_vertex, meta)


def _digest(data: HeadModelData) -> str:
    h = hashlib.sha256()
    for a in (data.v_template, data.faces, data.regions.get("face", np.zeros(0))):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(str(LAYOUT_VERSION).encode())
    return h.hexdigest()[:12]


def craft_layout(data: HeadModelData, rebuild: bool = False) -> UVLayout:
    """The cached HeadCraft layout of ``data`` (built on first use, a few seconds)."""
    from headforge.paths import cache_dir

    path = cache_dir() / f"{data.name}-craft-uv-{_digest(data)}.npz"
    if path.exists() and not rebuild:
        return UVLayout.load(path)
    layout = build_craft_layout(data)
    path.parent.mkdir(parents=True, exist_ok=True)
    layout.save(path)
    return layout
