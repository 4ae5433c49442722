"""The Neural Head Avatar: template head model + geometry network G + texture network T +
per-frame tracking parameters, rendered with headforge's differentiable rasterizer.

Coordinates: canonical head space (metres, y up, face +z); camera OpenCV at the origin with
x_cam = diag(1, -1, -1) x + translation (:mod:`headforge.head.pose`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import roma
import torch
from torch import nn

from headforge.avatars.base import Avatar, AvatarRender, Geometry
from headforge.avatars.nha.networks import GeometryNet, TextureNet
from headforge.errors import HeadforgeError
from headforge.head.landmarks import FACE_OVAL_LOOP
from headforge.head.lbs import pose_to_rotmats, surface_points
from headforge.head.model import INNER_REGIONS, POSE_ARGS, HeadModel, HeadModelData
from headforge.head.pose import FRAME_KEYS, head_to_camera
from headforge.head.topology import (directed_edges, laplacian_smooth, open_neck_ring, remove_region, subdivide_head,
                                     vertex_normals)
from headforge.metrics.protocol import MOUTH_PAIRS
from headforge.render import mesh
from headforge.render.camera import Cameras, project_points
from headforge.render.matte import soft_matte
from headforge.render.shading import constant_sh, sh_shading

LIP_PAIRS = tuple(map(tuple, MOUTH_PAIRS.tolist()))  # MediaPipe inner-lip pairs: the mouth opening
# Laplacian weights per region (NHA App. Table 3 in spirit: stiff face and eyes, free scalp); the
# scalp's weight is NHAConfig.laplacian_scalp.
LAPLACIAN_WEIGHTS = {"neck": 1.0, "ears": 5.0, "face": 20.0, "lips": 20.0, "eyelids": 20.0,
                     "eyeballs": 50.0, "mouth_interior": 20.0}
# App. Table 3's Laplacian weights of the geometry stage (the joint stage doubles them), in
# precedence order: a vertex in several regions takes the last one's weight. Vertices in no listed
# region (lips, eyelids, mouth interior: FLAME's face mask holds them) take the face's.
TABLE3_LAPLACIAN = {"face": 0.05, "scalp": 0.05, "neck": 0.1, "lower_neck": 0.25, "forehead": 0.05, "nose": 0.025,
                    "ears": 25.0, "eye_region": 5.0, "eyeballs": 0.0}
# The 10 inner-lip landmark pairs of NHA's mouth condition (App. A.2.2; MediaPipe ids): the mouth's
# width, then upper/lower inner-lip pairs from the subject's right to left.
INNER_LIP_PAIRS_10 = ((78, 308), (191, 95), (80, 88), (81, 178), (82, 87), (13, 14), (312, 317), (311, 402),
                      (310, 318), (415, 324))
# MediaPipe outlines of the regions App. Table 3 names that open-head lacks (paper_regions)
EYE_REGION_LOOPS = ((156, 70, 63, 105, 66, 107, 55, 193, 245, 128, 121, 120, 119, 118, 117, 111, 143),  # subject's right
                    (383, 300, 293, 334, 296, 336, 285, 417, 465, 357, 350, 349, 348, 347, 346, 340, 372))
FOREHEAD_LOOP = (21, 54, 103, 67, 109, 10, 338, 297, 332, 284, 251, 300, 293, 334, 296, 336, 9, 107, 66, 105, 63, 70)
NOSE_LOOP = (168, 417, 465, 412, 399, 456, 420, 429, 358, 327, 326, 2, 97, 98, 129, 209, 198, 236, 174, 188, 245, 193)


def build_template(data: HeadModelData, subdivide: bool, remove_lower_neck: bool, close_mouth: bool = False,
                   table3_regions: bool = False) -> HeadModelData:
    """NHA's template (App. A.1): FLAME's mouth hole closed (``close_mouth``; FLAME only), 4-way
    subdivision (``subdivide``), lower neck removed (``remove_lower_neck``; headforge keeps it by
    default, see NHAConfig). ``table3_regions``: add the regions of App. Table 3 the head model
    lacks (eye surroundings, forehead, nose: :func:`paper_regions`)."""
    if close_mouth and data.name == "flame":
        data = close_flame_mouth(data)
    if table3_regions:
        data = paper_regions(data)
    if subdivide:
        data = subdivide_head(data)
    if remove_lower_neck and "lower_neck" in data.regions:
        data = remove_region(data, "lower_neck")
    return data


def close_flame_mouth(data: HeadModelData) -> HeadModelData:
    """FLAME with its mouth hole closed (App. A.1; :func:`close_hole_near` at the inner lips'
    landmarks, iBUG 60-67, or the lips region)."""
    from headforge.head.topology import close_hole_near

    if data.landmark_faces is not None and len(data.landmark_faces) == 68:
        v = torch.as_tensor(np.asarray(data.v_template), dtype=torch.float64)
        lmk = surface_points(v[None], torch.as_tensor(np.asarray(data.faces)), torch.as_tensor(data.landmark_faces),
                             torch.as_tensor(data.landmark_bary))[0].numpy()
        centre = lmk[60:68].mean(0)
    elif "lips" in data.regions:
        centre = np.asarray(data.v_template)[data.regions["lips"]].mean(0)
    else:
        raise HeadforgeError("closing FLAME's mouth needs its landmark_embedding.npy or FLAME_masks.pkl")
    return close_hole_near(data, centre)


def _inside_loop(data: HeadModelData, landmarks: np.ndarray, loop: tuple[int, ...], hull: bool = False,
                 depth: float = 0.01) -> np.ndarray:
    """(V,) bool: template vertices inside the frontal (x, y) polygon of ``landmarks[loop]`` (its
    convex hull with ``hull``) and no more than ``depth`` metres behind its rearmost point (the
    front surface only). ``landmarks``: (478, 3) on the template, metres."""
    from matplotlib.path import Path as Polygon
    from scipy.spatial import ConvexHull

    v = np.asarray(data.v_template)
    points = landmarks[list(loop)]
    outline = points[ConvexHull(points[:, :2]).vertices, :2] if hull else points[:, :2]
    return Polygon(outline).contains_points(v[:, :2]) & (v[:, 2] > points[:, 2].min() - depth)


def paper_regions(data: HeadModelData) -> HeadModelData:
    """``data`` with App. Table 3's regions it lacks -- ``eye_region`` (eye surroundings: from the
    brow to below the lower lid), ``forehead`` (above the brows, inside the face oval), ``nose`` --
    as the template vertices inside MediaPipe landmark outlines (EYE_REGION_LOOPS,
    FOREHEAD_LOOP, NOSE_LOOP), in front. Eyeballs, eye cavities and the mouth interior are left
    out. FLAME's masks give these regions directly (``eye_region``, ``forehead``, ``nose``);
    other models need the 478-point MediaPipe embedding."""
    from dataclasses import replace

    missing = [k for k in ("eye_region", "forehead", "nose") if k not in data.regions]
    if not missing:
        return data
    if data.landmark_faces is None or len(data.landmark_faces) != 478:
        raise HeadforgeError(f"head model {data.name!r} has no {', '.join(missing)} region(s), and defining them "
                             f"needs MediaPipe's 478 landmarks embedded on it")
    v = torch.as_tensor(np.asarray(data.v_template), dtype=torch.float64)
    lmk = surface_points(v[None], torch.as_tensor(np.asarray(data.faces)), torch.as_tensor(data.landmark_faces),
                         torch.as_tensor(data.landmark_bary))[0].numpy()
    inner = np.zeros(len(v), bool)
    for name in INNER_REGIONS:
        inner[data.regions.get(name, [])] = True
    eyes = [_inside_loop(data, lmk, loop, hull=True) for loop in EYE_REGION_LOOPS]
    masks = {"eye_region": eyes[0] | eyes[1], "forehead": _inside_loop(data, lmk, FOREHEAD_LOOP),
             "nose": _inside_loop(data, lmk, NOSE_LOOP, hull=True)}
    regions = dict(data.regions) | {k: np.nonzero(masks[k] & ~inner)[0] for k in missing}
    return replace(data, regions=regions)


def scalp_top_back(rest, scalp):
    """(V,) bool: the scalp's top-back, which a frontal clip rarely shows on its outline: ``scalp``
    vertices more than 6 cm above the centroid of ``rest`` and behind it. ``rest``: (V, 3) template
    in metres (+y up, +z forward); ``scalp``: (V,) bool. numpy or torch in, the same out."""
    centre = rest.mean(0)
    return scalp & (rest[:, 1] > centre[1] + 0.06) & (rest[:, 2] <= centre[2])


def face_oval_vertices(data: HeadModelData) -> np.ndarray:
    """(V,) bool: the template vertices inside MediaPipe's face-oval loop (FACE_OVAL_LOOP) --
    the face region that the detected oval outlines in an image. Inside = within the loop's
    frontal (x, y) polygon and in front of its rearmost point (which leaves the back of the
    head out). Needs the 478-point MediaPipe landmark embedding."""
    from matplotlib.path import Path as Polygon

    v = torch.as_tensor(np.asarray(data.v_template), dtype=torch.float64)
    landmarks = surface_points(v[None], torch.as_tensor(np.asarray(data.faces)), torch.as_tensor(data.landmark_faces),
                               torch.as_tensor(data.landmark_bary))[0].numpy()
    loop, v = landmarks[list(FACE_OVAL_LOOP)], v.numpy()
    inside = Polygon(loop[:, :2]).contains_points(v[:, :2])
    return inside & (v[:, 2] > loop[:, 2].min())


# NHA's semantic regions (Sec. 3.2: facial skin and neck, eyes, ears, hair) as far as a synth
# subject's labels name them: synth does not label the ears (they are head skin), so they join the
# skin; the template's scalp is where the hair grows.
SEMANTIC_CLASSES = ("skin", "eyes", "hair")


@dataclass(kw_only=True)
class Rendered(AvatarRender):
    """NHA's render: rgb (B, H, W, 3) antialiased on ``background``, coverage (B, H, W), landmarks
    (B, L, 3) camera space, and NHA's own extras."""

    face_region: torch.Tensor | None  # (B, H, W) antialiased coverage by the face-oval region, or None
    fragments: mesh.Fragments
    vertices: torch.Tensor  # (B, V, 3) camera space
    offsets: torch.Tensor  # (B, V, 3) canonical offsets
    albedo: torch.Tensor | None = None  # (B, H, W, 3) T's output before shading (``shading`` avatars), 0 off the mesh
    classes: torch.Tensor | None = None  # (B, H, W, C) antialiased coverage by each of SEMANTIC_CLASSES, or None


class NeuralHeadAvatar(Avatar):
    def __init__(self, template: HeadModelData, tracking: dict[str, torch.Tensor], config):
        super().__init__()
        # NHA's tanh joint limits: frame poses are raw parameters, the skinning sees the limited ones
        self.head = HeadModel(template, joint_limits=config.joint_limits)
        V = self.head.num_vertices
        rest = torch.as_tensor(template.v_template, dtype=torch.float32)
        centre, scale = rest.mean(0), (rest - rest.mean(0)).abs().max()
        self.register_buffer("positions", (rest - centre) / scale)  # template in [-1, 1]
        self.shape = nn.Parameter(tracking["shape"].float().clone()[:, : self.head.n_shape])
        self.frames = nn.ParameterDict({k: nn.Parameter(v) for k, v in self.params_from_tracking(tracking).items()})
        self.geometry_net = GeometryNet(V, config.embed_dim, config.geo_layers, config.geo_width, cond_dim=3,
                                        max_offset=config.max_offset)
        # the mouth condition (App. A.2.2): a rotation and inner-lip distances (mouth_condition)
        self.mouth_pairs = INNER_LIP_PAIRS_10 if config.mouth_condition == "neck10" else LIP_PAIRS
        self.mouth_rotation = "root_neck" if config.mouth_condition == "neck10" else "jaw"
        self.texture_net = TextureNet(config.tex_grid, config.tex_channels, config.tex_layers, config.tex_width,
                                      cond_dim=3 + len(self.mouth_pairs), mouth_grid_size=config.tex_mouth_grid,
                                      normal_channels=tuple(config.normal_channels), head_width=config.tex_head_width,
                                      mapping_width=config.tex_mapping_width, last_width=config.tex_last_width or None)
        faces = self.head.faces
        region = lambda name: self.head.region(name) if name in self.head.region_names else torch.zeros(0, dtype=torch.long)  # noqa: E731
        # dynamic (neck-pose dependent) offsets only on the neck, faded smoothly into the head
        neck = torch.zeros(V, 3)
        neck[region("neck")] = 1.0
        self.register_buffer("neck_fade", laplacian_smooth(neck, faces, 0.5, iterations=10)[:, :1])
        # the vertices with dynamic offsets: G's conditioned evaluation runs on these only
        self.register_buffer("neck_rows", torch.nonzero(self.neck_fade[:, 0] > 0)[:, 0], persistent=False)  # derived
        scalp = torch.zeros(V, dtype=torch.bool)
        scalp[region("scalp")] = True
        self.table3 = config.laplacian_regions == "table3"  # a Python flag: the joint stage doubles the weights
        if self.table3:  # App. Table 3 (geometry stage)
            lap = torch.full((V,), TABLE3_LAPLACIAN["face"])
            for name, w in TABLE3_LAPLACIAN.items():
                lap[region(name)] = w
        else:
            lap = torch.full((V,), 1.0)
            for name, w in (LAPLACIAN_WEIGHTS | {"scalp": config.laplacian_scalp}).items():
                lap[region(name)] = w
        lap[scalp_top_back(rest, scalp)] *= config.laplacian_top_back_factor
        self.register_buffer("laplacian_weight", lap)
        self.laplacian_l1 = config.laplacian_norm == "l1"
        # A smooth offset field's umbrella Laplacian shrinks with the squared edge length: each 4-way
        # subdivision halves the edges, so without this factor the subdivided template's prior is
        # 16 times weaker (squared norm) than the one the weights were chosen on; a factor of 4 per
        # level restores it, one between 1 and 4 leaves it weaker (a Python float).
        levels = int(template.meta.get("subdivided", 0))
        self.laplacian_scale = config.laplacian_level_factor ** levels if config.laplacian_per_level else 1.0
        # Laplace-Beltrami (cotangent) weights of the template's 1-ring, fixed (App. A.3's lambda*)
        self.cotangent = config.laplacian_operator == "cotangent"
        cot_edges, cot_weights = (cotangent_weights(template.v_template, template.faces) if self.cotangent
                                  else (torch.zeros(0, 2, dtype=torch.long), torch.zeros(0)))
        self.register_buffer("cot_edges", cot_edges, persistent=False)  # derived
        self.register_buffer("cot_weights", cot_weights, persistent=False)  # derived
        # With laplacian_scalp_shell the scalp's Laplacian acts on the hair's thickness along the
        # template normal (and on the tangential rest): an even shell of hair costs nothing there,
        # so the thickness the outline measures on the top and sides may carry over to the unseen back.
        self.shell_laplacian = bool(config.laplacian_scalp_shell)  # a Python flag: no device sync per step
        self.register_buffer("shell_vertices", scalp & self.shell_laplacian, persistent=False)  # derived
        self.register_buffer("rest_normals", vertex_normals(rest[None], faces)[0], persistent=False)  # derived
        # With laplacian_face_cut the face's Laplacian averages over face (and ear, neck) neighbours
        # only: the stiff face (weight 20) is then not dragged along by hair grown on the free scalp.
        self.register_buffer("laplacian_edges", _edges_without_face_to_scalp(faces, region("face"), region("scalp"), V)
                             if config.laplacian_face_cut else torch.zeros(0, 2, dtype=torch.long), persistent=False)
        mouth = torch.zeros(V, dtype=torch.bool)
        mouth[region("lips")] = True
        mouth[region("mouth_interior")] = True
        self.register_buffer("mouth_faces", mouth[faces].any(1))
        inner = torch.zeros(V, dtype=torch.bool)
        inner[region("mouth_interior")] = True
        self.register_buffer("inner_mouth_faces", inner[faces].all(1), persistent=False)  # derived
        face = torch.zeros(V)
        face[region("face")] = 1.0
        self.register_buffer("face_vertices", face)
        scalp = torch.zeros(V, dtype=torch.bool)
        scalp[region("scalp")] = True
        edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        edges = torch.unique(torch.sort(edges, 1).values, dim=0)
        self.register_buffer("scalp_edges", edges[scalp[edges].all(1)])
        self.edge_mean = config.edge_mode == "mean"
        self.register_buffer("uv_corners", self.head.face_corner_uvs())
        # The rows above train_ring's mean row (the template's own open neck boundary: NHA's cut, or 3 cm
        # lower with the lower neck kept), with the protocol's head region, bound the area of the
        # training and fitting energies (method.energy_area).
        self.register_buffer("train_ring", torch.as_tensor(open_neck_ring(template), dtype=torch.long),
                             persistent=False)  # derived
        self.has_lips = self.head.num_landmarks == 478
        oval = face_oval_vertices(template) if self.has_lips else np.zeros(V, bool)
        self.register_buffer("face_oval", torch.as_tensor(oval, dtype=torch.float32)[:, None], persistent=False)  # derived
        outline = torch.ones(V, dtype=torch.bool)  # vertices that can form the outer silhouette
        for name in INNER_REGIONS:
            outline[region(name)] = False
        self.register_buffer("outline_vertices", torch.nonzero(outline)[:, 0], persistent=False)  # derived
        # The surfaces inside the head, which no silhouette or normal term reaches (w_offset_inner):
        # (V,) 1.0 on them. Left to the photometric term, they drifted through the face.
        self.register_buffer("inner_vertices", (~outline).float(), persistent=False)  # derived
        # soft edge of the rendered matte (headforge.render.matte): sigma in px at the training
        # resolution, fitted after training (trainer.fit_matte); 0 = the antialiased edge
        self.register_buffer("matte_sigma", torch.zeros(()))
        self.register_buffer("matte_resolution", torch.tensor(float(config.resolution)))
        # Optional (config.shading, beyond NHA): T's output is an albedo, lit by a learned 2nd-order SH
        # environment fixed to the dataset camera at the pixel's rendered normal -- a shape-from-shading
        # path from the photometric term to the normals that the albedo cannot absorb where it is
        # kept piecewise smooth (trainer's albedo_tv term).
        self.sh = nn.Parameter(constant_sh(1.0)) if config.shading else None

    # ---- geometry ------------------------------------------------------------------------
    def offsets(self, neck_pose: torch.Tensor) -> torch.Tensor:
        """(B, V, 3): static offsets everywhere, neck-pose dependent ones on the neck (blended
        into the static ones by ``neck_fade``). The conditioned network runs on the vertices the
        fade reaches (``neck_rows``) only: elsewhere the blend is the static offset exactly, and
        evaluating G there for every frame made up most of a per-frame alignment step."""
        B = neck_pose.shape[0]
        static = self.geometry_net(self.positions, neck_pose.new_zeros(1, 3))
        if B == 0:
            return static
        rows = self.neck_rows
        dynamic = self.geometry_net(self.positions, neck_pose, rows)  # (B, R, 3)
        near = static[:, rows]
        return static.repeat(B, 1, 1).index_copy(1, rows, near + self.neck_fade[rows] * (dynamic - near))

    def params_from_tracking(self, tracked: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Frame parameters (FRAME_KEYS, (T, ...) float32) that pose this avatar as ``tracked``
        (a dataset's tracking: poses as the skinning uses them) does: with joint limits, the
        raw poses whose limited values are the tracked ones."""
        params = {k: tracked[k].float().clone() for k in FRAME_KEYS}
        return params | self.head.effective_poses({k: params[k] for k in POSE_ARGS}, raw=True)

    def frame_params(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: self.frames[k][idx] for k in FRAME_KEYS}

    def pose(self, params: dict[str, torch.Tensor]):
        """Camera-space vertices (B, V, 3), landmarks (B, L, 3), offsets (B, V, 3)."""
        B = params["translation"].shape[0]
        offsets = self.offsets(params["neck_pose"])
        out = self.head(shape=self.shape.expand(B, -1), offsets=offsets,
                        **{k: params[k] for k in FRAME_KEYS if k != "translation"})
        verts = head_to_camera(out.vertices, params["translation"])
        lmk = None
        if out.landmarks is not None:
            # Landmarks steer the tracking parameters, not G: detected landmarks are noisy from frame
            # to frame, and through the shared network they drowned the silhouette's hair signal.
            lmk_out = self.head(shape=self.shape.expand(B, -1), offsets=offsets.detach(),
                                **{k: params[k] for k in FRAME_KEYS if k != "translation"})
            lmk = head_to_camera(lmk_out.landmarks, params["translation"])
        return verts, lmk, offsets

    def mouth_condition(self, params: dict[str, torch.Tensor], landmarks: torch.Tensor | None) -> torch.Tensor:
        """(B, 3 + P): NHA's mouth condition -- a rotation (axis-angle) and the distances (cm)
        of P inner-lip landmark pairs of the posed model (``mouth_pairs``; zeros for models
        without MediaPipe's landmarks). ``quick``: the effective (limited) jaw rotation and 3
        pairs; App. A.2.2 (``mouth_condition`` neck10): the rotation that applies to the mouth
        region, global (root) composed with neck, and 10 pairs."""
        if landmarks is not None and self.has_lips:
            d = torch.stack([(landmarks[:, a] - landmarks[:, b]).norm(dim=-1) for a, b in self.mouth_pairs], -1) * 100
        else:
            d = params["jaw_pose"].new_zeros(params["jaw_pose"].shape[0], len(self.mouth_pairs))
        if self.mouth_rotation == "jaw":
            rotation = self.head.effective_poses({"jaw_pose": params["jaw_pose"]})["jaw_pose"]
        else:
            poses = self.head.effective_poses({k: params[k] for k in ("root_pose", "neck_pose")})
            rotation = roma.rotmat_to_rotvec(pose_to_rotmats(poses["root_pose"]) @ pose_to_rotmats(poses["neck_pose"]))
        return torch.cat([rotation, d], -1)

    # ---- rendering -----------------------------------------------------------------------
    def render(self, params: dict[str, torch.Tensor], cameras: Cameras, background: float = 1.0,
               texture: bool = True, face_region: bool = False, matte: bool = True, normals: bool = False,
               classes: bool = False) -> Rendered:
        """``face_region``: also render the face-oval region's coverage (models with MediaPipe
        landmarks; None otherwise). ``matte``: soften the edge of ``rgb`` and ``coverage`` by the
        fitted ``matte_sigma`` (scaled to the camera's height); off, they are the antialiased
        render (the training losses use that). ``normals``: the camera-space normal map;
        ``classes``: the antialiased coverage by each of :data:`SEMANTIC_CLASSES` (both with
        gradients to the vertices; NHA's normal and semantic terms)."""
        verts, lmk, offsets = self.pose(params)
        faces = self.head.faces
        frags = mesh.rasterize(cameras, verts.detach(), faces)
        B, H, W = frags.face_id.shape
        hit = frags.face_id >= 0
        rgb = verts.new_full((B, H, W, 3), background)
        albedo = None
        bary = mesh.barycentrics(frags, cameras, verts, faces) if (texture or normals or classes) and hit.any() else None
        normal_map = None
        if normals and bary is not None:
            n = mesh.interpolate(vertex_normals(verts, faces), frags, faces, bary)
            normal_map = torch.nn.functional.normalize(n, dim=-1) * hit[..., None]
        if texture and hit.any():
            fid = frags.face_id[hit]
            b = bary[hit]  # (N, 3)
            canon = (self.positions[faces[fid]] * b[..., None]).sum(1)
            uv = (self.uv_corners[fid] * b[..., None]).sum(1)
            cond = self.mouth_condition(params, lmk)
            batch = torch.nonzero(hit)[:, 0]
            patches, normals = self._normal_patches(verts, frags, bary, hit)
            colour = self.texture_net(canon, uv, cond[batch], self.mouth_faces[fid], patches,
                                      self.inner_mouth_faces[fid])
            pixels = tuple(torch.nonzero(hit).T)
            if self.sh is not None:
                albedo = verts.new_zeros((B, H, W, 3)).index_put(pixels, colour)
                colour = colour * sh_shading(torch.nn.functional.normalize(normals, dim=-1), self.sh).clamp(min=0)
            rgb = rgb.index_put(pixels, colour)
        channels = [rgb, hit[..., None].to(verts.dtype)]
        face_region = face_region and self.has_lips
        if face_region:
            channels.append(self._face_region(frags, cameras, verts))
        if classes:
            table = self.semantic_classes().to(verts)
            channels.append(mesh.interpolate(table, frags, faces, bary) if bary is not None
                            else verts.new_zeros((B, H, W, table.shape[1])))
        out = mesh.antialias(torch.cat(channels, -1), frags, cameras, verts, faces)
        rgb, coverage = out[..., :3], out[..., 3].clamp(0, 1)
        if matte and self.matte_sigma > 0:
            rgb, coverage = soft_matte(rgb, coverage, float(self.matte_sigma * H / self.matte_resolution), background)
        first = 5 if face_region else 4
        return Rendered(rgb, coverage, landmarks=lmk, normals=normal_map,
                        face_region=out[..., 4].clamp(0, 1) if face_region else None,
                        fragments=frags, vertices=verts, offsets=offsets, albedo=albedo,
                        classes=out[..., first:].clamp(0, 1) if classes else None)

    def semantic_classes(self) -> torch.Tensor:
        """(V, C) one-hot of each template vertex's class in :data:`SEMANTIC_CLASSES` (all zero:
        no class -- the mouth's inside, which NHA's semantic term leaves out): the template's
        regions, or the table :meth:`set_semantic_classes` gave."""
        if getattr(self, "_semantic_classes", None) is None:
            table = torch.zeros(self.head.num_vertices, len(SEMANTIC_CLASSES))
            table[:, SEMANTIC_CLASSES.index("skin")] = 1.0
            for name, region in (("eyes", "eyeballs"), ("hair", "scalp"), (None, "mouth_interior")):
                if region in self.head.region_names:
                    rows = self.head.region(region)
                    table[rows] = 0.0
                    if name is not None:
                        table[rows, SEMANTIC_CLASSES.index(name)] = 1.0
            self._semantic_classes = table
        return self._semantic_classes

    def set_semantic_classes(self, table: torch.Tensor) -> None:
        """Replace the template regions' classes by ``table`` (V, C), e.g. the subject's own
        (:func:`headforge.avatars.nha.method.classes_from_labels`); not saved with the weights."""
        if table.shape != (self.head.num_vertices, len(SEMANTIC_CLASSES)):
            raise HeadforgeError(f"a semantic class table must be ({self.head.num_vertices}, {len(SEMANTIC_CLASSES)}), "
                                 f"got {tuple(table.shape)}")
        self._semantic_classes = table.detach().float().cpu()

    @torch.no_grad()
    def geometry(self, params: dict[str, torch.Tensor]) -> Geometry:
        """The posed mesh in camera space; face = the template's face region, head = all but the neck."""
        head = self.head
        face = torch.zeros(head.num_vertices, dtype=torch.bool)
        face[head.region("face")] = True
        keep = torch.ones(head.num_vertices, dtype=torch.bool)
        if "neck" in head.region_names:
            keep[head.region("neck")] = False
        return Geometry(self.pose(params)[0], head.faces, face_vertices=face, head_vertices=keep)

    def export(self, output, fmt: str, frames: list[int] | None = None, texture_size: int = 512, clip=None):
        from headforge.avatars.nha.export import export_run

        return export_run(self, output, fmt, frames, texture_size, clip)

    def export_formats(self) -> tuple[str, ...]:
        from headforge.avatars.nha.export import FORMATS

        return FORMATS

    def _face_region(self, frags: mesh.Fragments, cameras: Cameras, verts: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 1) interpolated face-oval indicator, with gradients to the vertices so the
        region's inner border moves too. Only triangles straddling that border get
        differentiable barycentrics: inside the others the value is constant, whatever the
        barycentrics, so its gradient is exactly zero (the same result as interpolating with
        :func:`mesh.barycentrics` everywhere, at a fraction of the backward cost)."""
        faces = self.head.faces
        oval = self.face_oval.to(verts.dtype)
        region = mesh.interpolate(oval, frags, faces)  # values; no vertex gradients
        corners = oval[faces, 0]  # (F, 3)
        straddles = corners.amax(1) != corners.amin(1)
        border = frags.mask & straddles[frags.face_id.clamp(min=0)]
        if border.any():
            bary = mesh.barycentrics(frags, cameras, verts, faces, pixels=border)  # (N, 3)
            value = (bary * corners[frags.face_id[border]]).sum(-1, keepdim=True)
            region = region.index_put(tuple(border.nonzero().T), value)
        return region

    def _normal_patches(self, verts: torch.Tensor, frags, bary: torch.Tensor, hit: torch.Tensor):
        """(N, C) normal-encoder features of the covered pixels, from the rendered camera-space
        normals, and those normals (N, 3; interpolated, not renormalised). The convolutions run
        on the covered pixels' bounding box plus a margin of the encoder's receptive radius,
        which gives the same features as the whole image."""
        faces = self.head.faces
        normals = mesh.interpolate(vertex_normals(verts, faces), frags, faces, bary)  # (B, H, W, 3)
        margin = len(self.texture_net.normal_encoder.convs)
        ys, xs = torch.nonzero(hit.any(0), as_tuple=True)
        y0, y1 = max(int(ys.min()) - margin, 0), min(int(ys.max()) + margin + 1, hit.shape[1])
        x0, x1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + margin + 1, hit.shape[2])
        feats = self.texture_net.encode_normals(normals[:, y0:y1, x0:x1])
        return feats[hit[:, y0:y1, x0:x1]], normals[hit]

    def contour_points(self, vertices: torch.Tensor, K: torch.Tensor, max_cos: float = 0.25) -> list[torch.Tensor]:
        """Per frame, the projected pixels (N_b, 2) of vertices on the silhouette rim: their
        normal is nearly perpendicular to the viewing ray (|cos| < ``max_cos``)."""
        v = vertices[:, self.outline_vertices]
        n = vertex_normals(vertices, self.head.faces)[:, self.outline_vertices]
        cos = (n * torch.nn.functional.normalize(v, dim=-1)).sum(-1).detach()
        px = project_points(v, K)
        return [px[b][cos[b].abs() < max_cos] for b in range(len(v))]

    # ---- regularisers ----------------------------------------------------------------------
    def laplacian_term(self, offsets: torch.Tensor, stage: str | None = None) -> torch.Tensor:
        """Region-weighted Laplacian of the offsets (B, V, 3) (= the Laplacian of the offset mesh
        minus that of the template, NHA's E_reg,lapl), the mean over vertices and frames.

        ``quick``: the uniform (umbrella) Laplacian, squared -- rather than NHA's L1: an L1
        subgradient keeps its full size on an already smooth face and, through the shared network,
        drowned the silhouette signal that grows hair. ``paper`` (App. A.3): the template's
        Laplace-Beltrami operator (``laplacian_operator`` cotangent), L1 over the components
        (``laplacian_norm`` l1), Table 3's weights doubled in the ``joint`` stage. On
        ``shell_vertices`` the Laplacian is that of (tangential offset, thickness along the
        template normal) instead. On a subdivided template the offsets are scaled by
        ``laplacian_scale`` first (``laplacian_per_level``), so a smooth field costs what it costs
        on the tracked template."""
        if self.laplacian_scale != 1.0:
            offsets = offsets * self.laplacian_scale
        norm = (lambda d: d.abs().sum(-1)) if self.laplacian_l1 else (lambda d: d.pow(2).sum(-1))  # noqa: E731
        energy = norm(self._laplacian(offsets))
        if self.shell_laplacian:
            thickness = (offsets * self.rest_normals).sum(-1, keepdim=True)
            split = torch.cat([offsets - thickness * self.rest_normals, thickness], -1)  # (B, V, 4)
            energy = torch.where(self.shell_vertices, norm(self._laplacian(split)), energy)
        weight = self.laplacian_weight * (2.0 if self.table3 and stage == "joint" else 1.0)
        return (energy * weight).mean()

    def _laplacian(self, values: torch.Tensor) -> torch.Tensor:
        """(B, V, C): the configured Laplacian of per-vertex ``values`` -- cotangent
        (:meth:`_cotangent`) or uniform (:meth:`_umbrella`)."""
        return self._cotangent(values) if self.cotangent else self._umbrella(values)

    def _cotangent(self, values: torch.Tensor) -> torch.Tensor:
        """(B, V, C): sum_j w_ij (x_j - x_i) / sum_j |w_ij| over each vertex's 1-ring, w_ij the
        template's cotangent weights (``cot_edges``, ``cot_weights``: :func:`cotangent_weights`) --
        the Laplace-Beltrami operator, normalised so it is in the units of ``values``. Zero on
        any function linear over a flat patch."""
        return apply_laplacian(values, self.cot_edges, self.cot_weights)

    def _umbrella(self, values: torch.Tensor) -> torch.Tensor:
        """(B, V, C): mean of each vertex's neighbours minus the vertex; with the face cut the
        face's neighbours exclude the scalp (``laplacian_edges``)."""
        if len(self.laplacian_edges) == 0:  # the shipped path, kept bit-identical to the measured runs
            return laplacian_smooth(values, self.head.faces, 1.0, iterations=1) - values
        i, j = self.laplacian_edges.T
        V = self.head.num_vertices
        degree = torch.zeros(V, dtype=values.dtype, device=values.device).index_add_(0, i, torch.ones_like(i, dtype=values.dtype))
        mean = torch.zeros_like(values).index_add_(-2, i, values.index_select(-2, j)) / degree.clamp(min=1)[:, None]
        return mean - values

    def edge_term(self, vertices: torch.Tensor) -> torch.Tensor:
        """NHA's scalp edge-length term on ``vertices`` (B, V, 3), the mean over scalp edges and
        frames. ``edge_mode`` template (``quick``): relative to the template, scalp edges stretched
        beyond 1.5x their template length (large hair offsets) are penalised by the excess ratio.
        ``mean`` (App. A.3): an edge e_i longer than 1.5x the frame's mean scalp edge e_bar costs
        (e_i - e_bar) / e_bar -- the paper's e_i - e_bar in units of e_bar (held constant), so the
        weight does not depend on the mesh density."""
        if len(self.scalp_edges) == 0:
            return vertices.new_zeros(())
        a, b = self.scalp_edges[:, 0], self.scalp_edges[:, 1]
        e = (vertices[:, a] - vertices[:, b]).norm(dim=-1)
        if self.edge_mean:
            mean = e.mean(-1, keepdim=True).detach()
            return torch.where(e > 1.5 * mean, e / mean - 1, torch.zeros_like(e)).mean()
        e0 = (self.head.v_template[a] - self.head.v_template[b]).norm(dim=-1).clamp(min=1e-6)
        return torch.relu(e / e0 - 1.5).mean()


def cotangent_weights(vertices: np.ndarray, faces: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The cotangent Laplacian of a mesh ((V, 3) metres, (F, 3)) as directed 1-ring edges
    (E, 2) long i -> j and weights (E,) float32: w_ij = (cot a_ij + cot b_ij) / 2 (libigl's
    cotmatrix), divided by sum_j |w_ij| so each vertex's row sums to one in absolute value."""
    import igl
    import scipy.sparse as sp

    L = sp.coo_matrix(igl.cotmatrix(np.asarray(vertices, np.float64), np.asarray(faces, np.int64)))
    off = L.row != L.col
    i, j, w = L.row[off], L.col[off], L.data[off]
    total = np.bincount(i, weights=np.abs(w), minlength=len(vertices))
    w = w / np.maximum(total[i], 1e-12)
    return torch.as_tensor(np.stack([i, j], 1), dtype=torch.long), torch.as_tensor(w, dtype=torch.float32)


def apply_laplacian(values: torch.Tensor, edges: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(..., V, C): sum_j w_ij (x_j - x_i) over the directed edges i -> j (``edges`` (E, 2) long,
    ``weights`` (E,)) of per-vertex ``values`` (..., V, C)."""
    i, j = edges.T
    diff = values.index_select(-2, j) - values.index_select(-2, i)
    return torch.zeros_like(values).index_add_(-2, i, weights.to(values.dtype)[:, None] * diff)


def _edges_without_face_to_scalp(faces: torch.Tensor, face: torch.Tensor, scalp: torch.Tensor, V: int) -> torch.Tensor:
    """(E, 2) unique directed mesh edges i -> j (both directions of every edge) except those from
    a ``face`` vertex to a ``scalp`` vertex."""
    i, j = directed_edges(faces, V)
    is_face = torch.zeros(V, dtype=torch.bool)
    is_face[face] = True
    is_scalp = torch.zeros(V, dtype=torch.bool)
    is_scalp[scalp] = True
    keep = ~(is_face[i] & is_scalp[j])
    return torch.stack([i[keep], j[keep]], 1)
