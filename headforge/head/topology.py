"""Topology tools the seed papers need on the head template.

- NHA (App. A.1): 4-way uniform subdivision carrying every per-vertex attribute and region,
  closing the mouth cavity, cutting the lower neck: :func:`subdivide_head`,
  :func:`close_hole_near`, :func:`remove_region`.
- HeadCraft (supp.): consistent subdivision -- subdivide once, keep (face, barycentric) per
  new vertex so every identity gets the same topology: :class:`ConsistentSubdivision`; and
  per-region Laplacian smoothing: :func:`laplacian_smooth`.
- Vertex normals and per-vertex tangent frames (TBN): :func:`vertex_normals`, :func:`tbn_frames`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.geometry import vertex_normals  # noqa: F401  (re-exported: the head floor's users import it here)
from headforge.head.model import HeadModelData


# ---- 4-way (midpoint) subdivision -------------------------------------------------------
@dataclass
class Subdivision:
    """One 4-way split of a triangle mesh.

    New vertex i (i >= V) is the midpoint of ``edges[i - V]``. Child face ``4 f + k`` lies in
    parent face f: k = 0..2 at the corners, k = 3 in the middle.
    """

    n_vertices: int  # V before
    edges: np.ndarray  # (E, 2) parent vertex pair of each new vertex
    faces: np.ndarray  # (4F, 3) new faces

    def carry(self, attribute: np.ndarray) -> np.ndarray:
        """Per-vertex attribute (V, ...) -> (V + E, ...) with midpoints averaged."""
        mid = 0.5 * (attribute[self.edges[:, 0]] + attribute[self.edges[:, 1]])
        return np.concatenate([attribute, mid.astype(attribute.dtype)], axis=0)

    def carry_region(self, ids: np.ndarray) -> np.ndarray:
        """A new vertex joins a region when both of its parents are in it."""
        inside = np.zeros(self.n_vertices, dtype=bool)
        inside[ids] = True
        mid = inside[self.edges[:, 0]] & inside[self.edges[:, 1]]
        return np.concatenate([ids, self.n_vertices + np.nonzero(mid)[0]])

    def child_point(self, face_ids: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Re-express points given as (parent face, barycentric) on the child faces."""
        b = np.asarray(bary, np.float64)
        k = np.full(len(b), 3)
        for corner in range(3):
            k[b[:, corner] >= 0.5] = corner
        out = np.empty_like(b)
        # Corner child c keeps corner c and the two midpoints next to it (order of _split).
        for corner in range(3):
            sel = k == corner
            a, n1, n2 = corner, (corner + 1) % 3, (corner + 2) % 3
            out[sel, 0] = 2 * b[sel, a] - 1
            out[sel, 1] = 2 * b[sel, n1]
            out[sel, 2] = 2 * b[sel, n2]
        sel = k == 3  # middle child (m01, m12, m20)
        out[sel, 0] = 1 - 2 * b[sel, 2]
        out[sel, 1] = 1 - 2 * b[sel, 0]
        out[sel, 2] = 1 - 2 * b[sel, 1]
        return 4 * np.asarray(face_ids) + k, out


def subdivide(faces: np.ndarray, n_vertices: int) -> Subdivision:
    """4-way split every triangle of ``faces`` (F, 3) on ``n_vertices`` vertices."""
    faces = np.asarray(faces, np.int64)
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(pairs, axis=1)
    edges, inverse = np.unique(key, axis=0, return_inverse=True)
    mid = n_vertices + inverse.reshape(3, -1).T  # (F, 3): m01, m12, m20
    v0, v1, v2 = faces.T
    m01, m12, m20 = mid.T
    children = np.stack([
        np.stack([v0, m01, m20], 1),
        np.stack([v1, m12, m01], 1),
        np.stack([v2, m20, m12], 1),
        np.stack([m01, m12, m20], 1),
    ], axis=1).reshape(-1, 3)
    return Subdivision(n_vertices, edges, children)


def subdivide_head(data: HeadModelData) -> HeadModelData:
    """NHA's template subdivision: every per-vertex quantity, region, UV and landmark carried."""
    V = len(data.v_template)
    geo = subdivide(data.faces, V)
    uv = subdivide(data.uv_faces, len(data.uvs))
    per_vertex = lambda a: None if a is None else geo.carry(a)  # noqa: E731
    j_regressor = np.concatenate([data.j_regressor, np.zeros((len(data.j_regressor), len(geo.edges)))], axis=1)
    lmk_faces, lmk_bary = data.landmark_faces, data.landmark_bary
    if lmk_faces is not None:
        lmk_faces, lmk_bary = geo.child_point(lmk_faces, lmk_bary)
    out = replace(data, v_template=geo.carry(data.v_template), faces=geo.faces, uvs=uv.carry(data.uvs),
                  uv_faces=uv.faces, shapedirs=geo.carry(data.shapedirs), exprdirs=geo.carry(data.exprdirs),
                  posedirs=per_vertex(data.posedirs), weights=geo.carry(data.weights), j_regressor=j_regressor,
                  landmark_faces=lmk_faces, landmark_bary=lmk_bary,
                  regions={k: geo.carry_region(v) for k, v in data.regions.items()},
                  meta={**data.meta, "subdivided": data.meta.get("subdivided", 0) + 1})
    out.validate()
    return out


# ---- removing a region, closing a hole ----------------------------------------------------
def remove_region(data: HeadModelData, region: str) -> HeadModelData:
    """Drop the faces touching ``region`` (e.g. NHA's 'lower_neck') and unused vertices."""
    if region not in data.regions:
        raise HeadforgeError(f"head model {data.name!r} has no region {region!r}")
    drop = np.zeros(len(data.v_template), dtype=bool)
    drop[data.regions[region]] = True
    keep_face = ~drop[data.faces].any(axis=1)
    faces = data.faces[keep_face]
    used = np.unique(faces)
    remap = np.full(len(data.v_template), -1)
    remap[used] = np.arange(len(used))
    lmk_faces, lmk_bary = data.landmark_faces, data.landmark_bary
    if lmk_faces is not None:
        face_remap = np.cumsum(keep_face) - 1
        if not keep_face[lmk_faces].all():
            raise HeadforgeError(f"removing {region!r} would remove landmark triangles")
        lmk_faces = face_remap[lmk_faces]
    regions = {k: remap[v][remap[v] >= 0] for k, v in data.regions.items() if k != region}
    pick = lambda a: None if a is None else a[used]  # noqa: E731
    out = replace(data, v_template=data.v_template[used], faces=remap[faces], uv_faces=data.uv_faces[keep_face],
                  shapedirs=data.shapedirs[used], exprdirs=data.exprdirs[used], posedirs=pick(data.posedirs),
                  weights=data.weights[used], j_regressor=_joint_regressor_on(data, used), regions=regions,
                  landmark_faces=lmk_faces, landmark_bary=lmk_bary,
                  meta={**data.meta, "removed_regions": data.meta.get("removed_regions", []) + [region]})
    out.validate()
    return out


def _joint_regressor_on(data: HeadModelData, used: np.ndarray) -> np.ndarray:
    """(J, len(used)) joint regressor on a vertex subset that gives the same joints as the full
    one for every shape and expression. Joints are linear in the template and the blend
    directions; when the dropped vertices carry regressor weight (a neck joint regressed from
    the lower neck), the weights are re-solved by least squares on the kept vertices -- simply
    dropping those columns moved the neck and head joints and the posed head by ~8 mm."""
    dropped = np.ones(len(data.v_template), dtype=bool)
    dropped[used] = False
    if not np.abs(data.j_regressor[:, dropped]).any():
        return data.j_regressor[:, used]
    basis = np.concatenate([data.v_template[:, :, None], data.shapedirs, data.exprdirs], axis=2)  # (V, 3, K)
    target = np.einsum("jv,vck->jck", data.j_regressor, basis).reshape(len(data.j_regressor), -1)
    kept = basis[used].reshape(len(used), -1)  # (U, 3K)
    solution = np.linalg.lstsq(kept.T.astype(np.float64), target.T.astype(np.float64), rcond=None)[0]  # (U, J)
    regressor = solution.T.astype(data.j_regressor.dtype)
    scale = np.abs(target).max()
    error = np.abs(regressor @ kept - target).max()
    if error > 1e-5 * max(scale, 1.0):
        raise HeadforgeError(f"cannot keep the joints when removing vertices (residual {error:.2e})")
    return regressor


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed loops of boundary edges, each as an ordered vertex array."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = edges[counts[inverse] == 1]  # oriented as in their only face
    nxt = {int(a): int(b) for a, b in boundary}
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen and v in nxt:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(np.array(loop))
    return loops


def close_hole_near(data: HeadModelData, point: np.ndarray) -> HeadModelData:
    """Close the boundary loop nearest ``point`` (e.g. FLAME's mouth opening, NHA App. A.1)
    with a fan around a new centre vertex whose attributes are the loop's mean."""
    loops = boundary_loops(data.faces)
    if not loops:
        raise HeadforgeError("the mesh has no hole to close")
    dist = [np.linalg.norm(data.v_template[l].mean(0) - point) for l in loops]
    loop = loops[int(np.argmin(dist))]
    centre = len(data.v_template)
    # Boundary edges run a->b in their face; the fan runs b->a to keep orientation consistent.
    fan = np.stack([np.roll(loop, -1), loop, np.full(len(loop), centre)], axis=1)
    mean = lambda a: None if a is None else np.concatenate([a, a[loop].mean(0, keepdims=True)])  # noqa: E731
    uv_centre = len(data.uvs)
    corner_uv = {}
    for f, uf in zip(data.faces, data.uv_faces):
        for v, u in zip(f, uf):
            corner_uv.setdefault(int(v), int(u))
    uv_fan = np.stack([[corner_uv[int(v)] for v in np.roll(loop, -1)], [corner_uv[int(v)] for v in loop],
                       np.full(len(loop), uv_centre)], axis=1)
    uvs = np.concatenate([data.uvs, data.uvs[uv_fan[:, 1]].mean(0, keepdims=True)])
    out = replace(data, v_template=mean(data.v_template), faces=np.concatenate([data.faces, fan]),
                  uvs=uvs, uv_faces=np.concatenate([data.uv_faces, uv_fan]), shapedirs=mean(data.shapedirs),
                  exprdirs=mean(data.exprdirs), posedirs=mean(data.posedirs), weights=mean(data.weights),
                  j_regressor=np.concatenate([data.j_regressor, np.zeros((len(data.j_regressor), 1))], axis=1),
                  meta={**data.meta, "closed_holes": data.meta.get("closed_holes", 0) + 1})
    out.validate()
    return out


# ---- consistent subdivision (HeadCraft) ---------------------------------------------------
class ConsistentSubdivision:
    """Subdivide a template once; every later mesh with the template's topology gets the
    same dense topology by evaluating stored (parent face, barycentric) pairs.

    Args:
        faces: (F, 3) template faces; n_vertices: V; levels: number of 4-way splits.
    """

    def __init__(self, faces: np.ndarray, n_vertices: int, levels: int = 1):
        faces = np.asarray(faces, np.int64)
        F = len(faces)
        # Track each vertex as barycentric weights over the corners of an original face.
        owner = np.zeros(n_vertices, np.int64)
        weights = np.zeros((n_vertices, 3))
        for k in range(3):
            owner[faces[:, k]] = np.arange(F)
        for k in range(3):
            match = faces[owner, k] == np.arange(n_vertices)
            weights[match, k] = 1.0
        current, origin = faces, np.arange(F)  # origin[f]: original face of current face f
        V = n_vertices
        for _ in range(levels):
            step = subdivide(current, V)
            # Midpoint weights: both parents re-expressed in the owner face of the edge's first face.
            face_of_edge = np.zeros(len(step.edges), np.int64)
            pairs = np.sort(np.concatenate([current[:, [0, 1]], current[:, [1, 2]], current[:, [2, 0]]]), axis=1)
            _, inv = np.unique(pairs, axis=0, return_inverse=True)
            face_of_edge[inv] = np.tile(np.arange(len(current)), 3)
            orig = origin[face_of_edge]
            new_w = np.zeros((len(step.edges), 3))
            for end in range(2):
                v = step.edges[:, end]
                new_w += 0.5 * self._in_face(v, orig, owner, weights, faces)
            owner = np.concatenate([owner, orig])
            weights = np.concatenate([weights, new_w])
            origin = np.repeat(origin, 4)
            current, V = step.faces, V + len(step.edges)
        self.faces = current  # (F * 4**levels, 3)
        self.face_ids = owner  # (V', ) original face of each dense vertex
        self.bary = weights  # (V', 3)

    @staticmethod
    def _in_face(v, face, owner, weights, faces):
        """Barycentric weights of vertices ``v`` w.r.t. original faces ``face``."""
        out = np.zeros((len(v), 3))
        for k in range(3):
            corner = faces[owner[v], k]
            for j in range(3):
                out[:, j] += weights[v, k] * (faces[face, j] == corner)
        return out

    def apply(self, vertices: torch.Tensor | np.ndarray, faces: np.ndarray | None = None):
        """(..., V, 3) template-topology vertices -> (..., V', 3) dense vertices."""
        tri = torch.as_tensor(self._faces_t if faces is None else faces)
        v = torch.as_tensor(vertices)
        corners = v[..., tri[self.face_ids], :]  # (..., V', 3, 3)
        return (corners * torch.as_tensor(self.bary, dtype=v.dtype)[..., None]).sum(-2)

    def bind(self, faces: np.ndarray) -> "ConsistentSubdivision":
        self._faces_t = torch.as_tensor(np.asarray(faces, np.int64))
        return self


# ---- smoothing, normals, tangent frames ---------------------------------------------------
def directed_edges(faces: torch.Tensor, V: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Unique directed edges i -> j of a triangle mesh (both directions of every edge), sorted
    by (i, j): two (E,) long tensors."""
    i = torch.cat([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
    j = torch.cat([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
    key = torch.unique(i * V + j)
    return key // V, key % V


def laplacian_smooth(vertices: torch.Tensor, faces: torch.Tensor, strength: torch.Tensor | float = 0.5,
                     iterations: int = 1) -> torch.Tensor:
    """Classic uniform Laplacian smoothing, x <- x + s (mean(neighbours) - x).

    Args:
        vertices: (..., V, 3); faces: (F, 3) long.
        strength: scalar or (V,) per-vertex weight in [0, 1] -- 0 keeps a vertex fixed, which
            gives per-region smoothing (HeadCraft keeps subtle parts such as eyes and lips).
    """
    V = vertices.shape[-2]
    i, j = directed_edges(faces, V)
    degree = torch.zeros(V, dtype=vertices.dtype, device=vertices.device).index_add_(
        0, i, torch.ones_like(i, dtype=vertices.dtype))
    s = torch.as_tensor(strength, dtype=vertices.dtype, device=vertices.device)
    s = s[:, None] if s.ndim == 1 else s
    x = vertices
    for _ in range(iterations):
        total = torch.zeros_like(x).index_add_(-2, i, x.index_select(-2, j))
        mean = total / degree.clamp(min=1)[:, None]
        x = x + s * (mean - x)
    return x


def tbn_frames(vertices: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor, uv_faces: torch.Tensor) -> torch.Tensor:
    """Per-vertex orthonormal frames (..., V, 3, 3) with columns (tangent, bitangent, normal).

    The tangent follows +u of the UV map (Gram-Schmidt against the normal); the bitangent is
    normal x tangent, so frames are right-handed. HeadCraft expresses displacements in them.
    """
    tri = vertices[..., faces, :]
    tuv = uvs[uv_faces]  # (F, 3, 2)
    e1, e2 = tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    d1, d2 = tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    inv = torch.where(det.abs() > 1e-12, 1.0 / det, torch.zeros_like(det))
    face_t = (e1 * d2[:, 1, None] - e2 * d1[:, 1, None]) * inv[:, None]
    tangent = torch.zeros_like(vertices)
    for k in range(3):
        tangent = tangent.index_add(-2, faces[:, k], face_t)
    normal = vertex_normals(vertices, faces)
    tangent = tangent - (tangent * normal).sum(-1, keepdim=True) * normal
    tangent = torch.nn.functional.normalize(tangent, dim=-1, eps=1e-12)
    bitangent = torch.cross(normal, tangent, dim=-1)
    return torch.stack([tangent, bitangent, normal], dim=-1)


# ---- the neck cut ------------------------------------------------------------------------------
def boundary_vertices(faces: np.ndarray, V: int) -> np.ndarray:
    """Vertices on open boundary edges of ``faces`` (F, 3)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    return np.unique(uniq[counts == 1].ravel())


def faces_above_neck_cut(data: HeadModelData) -> np.ndarray:
    """(F,) bool: the faces NHA's neck cut keeps (those without a ``lower_neck`` vertex; all
    faces when the model has no such region)."""
    faces = np.asarray(data.faces)
    if "lower_neck" not in data.regions:
        return np.ones(len(faces), bool)
    lower = np.zeros(len(data.v_template), dtype=bool)
    lower[data.regions["lower_neck"]] = True
    return ~lower[faces].any(1)


def open_neck_ring(data: HeadModelData, faces: np.ndarray | None = None) -> np.ndarray:
    """Vertex indices of the open boundary of ``faces`` (default: the template's) on the neck:
    the neck the template has, down to its end. Falls back to any open boundary."""
    faces = np.asarray(data.faces) if faces is None else faces
    V = len(data.v_template)
    neck = np.zeros(V, dtype=bool)
    neck[data.regions.get("neck", [])] = True
    boundary = boundary_vertices(faces, V)
    ring = boundary[neck[boundary]]
    return ring if len(ring) else boundary


def neck_cut_ring(data: HeadModelData) -> np.ndarray:
    """Vertex indices of NHA's neck cut (App. A.1): the open boundary that removing the lower
    neck leaves (the same ring whether or not the template keeps its lower neck)."""
    return open_neck_ring(data, np.asarray(data.faces)[faces_above_neck_cut(data)])
