"""The PointAvatar avatar (Zheng et al., CVPR 2023): a canonical point cloud whose SDF-derived
normals and albedo come from one MLP, deformed by learned blendshapes and skinning into each
frame's pose, shaded by a normal-conditioned MLP and splatted.

Spaces (metres unless stated): the *canonical* points ``x_c`` (free, learned); the head model's
canonical pose ``x_o = x_c + O(x_c)`` (mouth open ``CANONICAL_JAW`` rad, the training clip's mean
expression, the authors' choice); the *deformed* (posed head) space

    x_d = M(x) [M_c(x)^-1 x_o - B_E(psi_c) - B_P(theta_c) + B_E(psi) + B_P(theta)]

with M = sum_j W_j A_j the blended skinning transform of the frame (A_j: the head model's joint
transforms; one more, static bone: identity), M_c the same at the canonical pose; then camera
space by :func:`headforge.head.pose.head_to_camera`. Normals: n_c = grad SDF (Eq. 1), deformed by
the inverse transpose of the Jacobian dx_d/dx_c (Eq. 6), computed exactly by forward-mode AD.
The networks see normalised points ``q = (x_c - centre) / SCALE``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from headforge.avatars.base import Avatar, AvatarRender, Geometry
from headforge.avatars.pointavatar.networks import AlbedoNet, CanonicalNet, Deformer, MouthAlbedoNet, ShadingNet
from headforge.errors import HeadforgeError
from headforge.head.landmarks import INNER_LIP_LOOP, N_MEDIAPIPE
from headforge.head.model import POSE_ARGS, HeadModel, HeadModelData
from headforge.head.pose import FLIP, FRAME_KEYS, head_to_camera
from headforge.render.camera import Cameras
from headforge.render.points import close_mask, splat
from headforge.render.shading import lambert, sh_shading

CANONICAL_JAW = 0.4  # rad, the canonical pose's jaw opening (authors' code)
SCALE = 0.15  # m: the networks' unit (a head is about +-1 of it around its centre)
INNER_REGIONS = ("mouth_interior", "eye_cavities")  # head-model regions FLAME's surface does not have
MOUTH_DEPTH = 0.015  # m: how far behind the lips' opening the seeded mouth points reach


@dataclass(kw_only=True)
class PointRender(AvatarRender):
    """PointAvatar's render: rgb, coverage, camera-space normals (when asked for), and per
    point: ``max_weight`` (B, N) the largest compositing weight and ``front`` (B, N) bool, the
    nearest on some pixel (what the prunes keep), ``points`` and
    ``point_normals`` (B, N, 3) the posed points and their unit normals in camera space;
    ``albedo`` / ``shading`` (B, H, W, 3) composited when asked for (pictures, relighting tests)."""

    max_weight: torch.Tensor
    front: torch.Tensor
    canonical: "Canonical"
    points: torch.Tensor
    point_normals: torch.Tensor
    albedo: torch.Tensor | None = None
    shading: torch.Tensor | None = None


@dataclass
class Canonical:
    """The frame-independent state of the cloud: normalised points q (N, 3), sdf (N,), the SDF
    gradient (N, 3, normalised units), albedo (N, 3); the deformer's hidden code h (N, width),
    skinning weights W (N, n_bones) and canonical offset O (N, 3, metres), and their derivatives
    along the three axes of q (each with a leading 3), or None when normals go by rotation only."""

    q: torch.Tensor
    sdf: torch.Tensor
    grad: torch.Tensor
    albedo: torch.Tensor
    h: torch.Tensor
    W: torch.Tensor
    O: torch.Tensor
    tangents: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None


class PointAvatarModel(Avatar):
    relightable = True  # render(..., light=...) (see colours)

    def __init__(self, data: HeadModelData, tracking: dict[str, torch.Tensor], canonical_expression: torch.Tensor,
                 config):
        super().__init__()
        self.head = HeadModel(data)
        self.config_flags(config)
        self.register_buffer("shape", tracking["shape"].float()[:, : self.head.n_shape].clone())
        self.frames = nn.ParameterDict({k: nn.Parameter(tracking[k].float().clone()) for k in FRAME_KEYS})
        self.register_buffer("canonical_expression", canonical_expression.float().reshape(1, -1).clone())
        J = len(self.head.parent_list)
        self.n_pose = 9 * (J - 1)
        # the head model at the canonical pose: the regulariser's nearest vertices and M_c
        with torch.no_grad():
            jaw = torch.tensor([[CANONICAL_JAW, 0.0, 0.0]])
            out = self.head(shape=self.shape, expression=self.canonical_expression, jaw_pose=jaw)
            A_c, p_c = self.head.skinning_transforms(self.shape, self.canonical_expression, {"jaw_pose": jaw})
        self.register_buffer("canonical_vertices", out.vertices[0], persistent=False)  # derived
        # the vertices the pseudo ground truth is taken from: FLAME's outer surface has no mouth or eye
        # cavity; open-head's cavity, skinned to the skull near the lips, took the points in the
        # canonical (open) mouth and pinned the tongue's and lower teeth's place to the skull (docs/pointavatar.md)
        inner = torch.zeros(len(out.vertices[0]), dtype=torch.bool)
        if not config.pseudo_gt_inner:
            for name in set(INNER_REGIONS) & set(self.head.region_names):
                inner[self.head.region(name)] = True
        self.register_buffer("target_vertices", torch.nonzero(~inner)[:, 0], persistent=False)  # derived
        self.register_buffer("canonical_transforms", self._with_static_bone(A_c)[0], persistent=False)
        self.register_buffer("canonical_pose_feature", p_c[0], persistent=False)
        self.register_buffer("centre", out.vertices[0].mean(0), persistent=False)
        # the head model's landmarks in the canonical (jaw-open) pose, x_o space: the avatar's own
        # landmarks are these positions deformed as cloud points there would be (own_landmarks)
        lmk = torch.zeros(0, 3) if out.landmarks is None else out.landmarks[0]
        self.register_buffer("canonical_landmarks", lmk.clone(), persistent=False)
        V = self.head.num_vertices
        exprdirs = self.head.blenddirs[self.head.n_shape:].reshape(-1, V, 3).transpose(0, 1)  # (V, n_expr, 3)
        self.register_buffer("vertex_exprdirs", exprdirs.contiguous(), persistent=False)
        if self.head.posedirs is not None:  # FLAME: pose correctives exist; open-head has none (P's target: 0)
            posedirs = self.head.posedirs.reshape(self.n_pose, V, 3).transpose(0, 1)
        else:
            posedirs = torch.zeros(V, self.n_pose, 3)
        self.register_buffer("vertex_posedirs", posedirs.contiguous(), persistent=False)
        weights = torch.cat([torch.zeros(V, 1), self.head.weights], 1)  # static bone first, weight 0 on the head
        self.register_buffer("vertex_weights", weights, persistent=False)
        n_bones = J + 1
        self.canonical_net = CanonicalNet(config.canonical_width, config.canonical_layers, config.canonical_skip,
                                          config.frequencies, config.init_radius)
        self.deformer = Deformer(config.deformer_width, config.deformer_layers, self.head.n_expr, self.n_pose, n_bones,
                                 offset=config.canonical_offset)
        self.albedo_net = (AlbedoNet(config.albedo_width, config.albedo_layers, config.albedo_frequencies)
                           if config.albedo_width > 0 else None)
        self.mouth_albedo_net = None
        if config.mouth_albedo_width > 0:
            if len(self.canonical_mouth) == 0:
                raise HeadforgeError("mouth_albedo_width > 0 needs a head model with MediaPipe's landmarks "
                                     "(the inner lips place the mouth); this one has none")
            self.mouth_albedo_net = MouthAlbedoNet(config.mouth_albedo_width, config.mouth_albedo_layers,
                                                   config.albedo_frequencies, self.head.n_expr + 3)
        self.mouth_albedo_radius = float(config.mouth_albedo_radius)
        self.shading_net = ShadingNet(config.shading_width, config.shading_layers) if config.shading != "none" else None
        self.colour_net = ShadingNet(config.shading_width, config.shading_layers, in_dim=6) if config.shading == "none" else None
        gen = torch.Generator().manual_seed(config.seed)
        if config.init_cloud == "head":  # the tracked head model's canonical surface (x_o = x_c: no offset yet)
            import trimesh

            mesh = trimesh.Trimesh(self.canonical_vertices.detach().numpy(), self.head.faces.numpy(), process=False)
            start, _ = trimesh.sample.sample_surface(mesh, config.init_points, seed=config.seed)  # area-uniform
            self.points = nn.Parameter((torch.from_numpy(start).float() - self.centre) / SCALE)
        else:
            self.points = nn.Parameter(sphere_points(config.init_points, config.init_radius, gen))
        radius = config.init_point_radius or initial_point_radius(config.init_points, config.init_radius)
        self.register_buffer("radius", torch.tensor(radius))  # world metres
        self.register_buffer("visible", torch.zeros(config.init_points, dtype=torch.bool))
        self.register_buffer("train_steps", torch.zeros((), dtype=torch.long))  # seeds the Eikonal samples: exact resume
        # (L, 2) pixels: where the head model's projected landmarks sit against the detections on the
        # training frames the avatar was trained at (method.landmark_bias); the fitting terms subtract it
        self.register_buffer("landmark_bias", torch.zeros(len(data.landmark_faces), 2))
        self._cache: tuple | None = None
        self._vertex_tree = None  # the canonical vertices' k-d tree (nearest_canonical_vertices)

    def config_flags(self, config) -> None:
        """The render-time switches of ``config`` kept on the avatar (plain Python values)."""
        self.jacobian_normals = bool(config.jacobian_normals)
        self.points_per_pixel = int(config.points_per_pixel)
        self.hole_filling = bool(config.hole_filling)
        self.surfel_min_cos = float(config.surfel_min_cos)

    @property
    def canonical_mouth(self) -> torch.Tensor:
        """(20, 3) the canonical inner-lip ring (x_o space, metres); (0, 3) for a head model
        without MediaPipe's landmarks."""
        if len(self.canonical_landmarks) != N_MEDIAPIPE:
            return self.canonical_landmarks[:0]
        return self.canonical_landmarks[list(INNER_LIP_LOOP)]

    def splat(self, cameras: Cameras, points: torch.Tensor, features: torch.Tensor, radius_px: torch.Tensor,
              normals: torch.Tensor):
        """Splat the points as the avatar draws them: discs, or surfels of ``normals`` (same frame
        as ``points``) when ``surfel_min_cos`` > 0."""
        surfels = {"normals": normals, "min_cos": self.surfel_min_cos} if self.surfel_min_cos > 0 else {}
        return splat(cameras, points, features, radius_px, K=self.points_per_pixel, **surfels)

    def nearest_canonical_vertices(self, points: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
        """(N,) index of the canonical head-model vertex nearest to each of ``points`` (N, 3,
        metres) among ``target_vertices`` (the outer surface unless ``pseudo_gt_inner``): a k-d
        tree built once on the CPU, chunked distances on a GPU."""
        if points.device.type == "cpu":
            if self._vertex_tree is None:
                from scipy.spatial import cKDTree

                self._vertex_tree = cKDTree(self.canonical_vertices[self.target_vertices].numpy())
            nearest = torch.from_numpy(self._vertex_tree.query(points.detach().numpy())[1]).long()
        else:
            targets = self.canonical_vertices[self.target_vertices]
            nearest = torch.cat([torch.cdist(p, targets).argmin(1) for p in points.detach().split(chunk)])
        return self.target_vertices[nearest]

    @staticmethod
    def _with_static_bone(A: torch.Tensor) -> torch.Tensor:
        """(B, J, 4, 4) -> (B, J + 1, 4, 4): an identity transform first (the shoulders' bone)."""
        eye = torch.eye(4, dtype=A.dtype, device=A.device).expand(A.shape[0], 1, 4, 4)
        return torch.cat([eye, A], 1)

    def params_from_tracking(self, tracked: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Frame parameters that pose this avatar as ``tracked`` (a dataset's tracking) does."""
        return {k: tracked[k].float().clone() for k in FRAME_KEYS}

    # ---- the canonical cloud --------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    def canonical(self, training: bool) -> Canonical:
        """The frame-independent outputs (see :class:`Canonical`); cached between calls while
        no parameter changed and gradients are off (rendering a sequence)."""
        own = [p for n, p in self.named_parameters() if not n.startswith("frames.")]
        # cacheable when nothing upstream needs gradients: rendering, and per-frame fitting, where
        # only the frame parameters train (the canonical state is then the same every step)
        frozen = not training and not (torch.is_grad_enabled() and any(p.requires_grad for p in own))
        # the device and dtype too: a move (.cuda(), .cpu(), .double()) must not serve the old device's state
        key = (self.n_points, self.jacobian_normals, self.points.device, self.points.dtype,
               tuple(p._version for p in own))
        if frozen and self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        q = self.points
        # the SDF sees the points' positions, not the reverse: the data term must not drag points
        # onto a smooth surface (authors' code); the gradient (normal) is differentiable
        sdf, grad, albedo = self.canonical_net.sdf_and_normal(q.detach(), create_graph=training)
        if self.albedo_net is not None:  # the separate albedo network replaces the canonical one's
            albedo = self.albedo_net(q.detach())
        if self.jacobian_normals:
            # forward-mode derivatives along q's three axes, stacked as 3N rows
            N = q.shape[0]
            t3 = torch.eye(3, dtype=q.dtype, device=q.device).repeat_interleave(N, 0)
            outs, tans = torch.func.jvp(self.deformer, (q.repeat(3, 1),), (t3,))
            h, W, O = (o[:N] for o in outs)
            tangents = tuple(t.reshape(3, N, *t.shape[1:]) for t in tans)
        else:
            h, W, O = self.deformer(q)
            tangents = None
        state = Canonical(q, sdf, grad, albedo, h, W, O, tangents)
        if frozen:
            state = Canonical(*(t.detach() if isinstance(t, torch.Tensor) else
                                tuple(x.detach() for x in t) if t is not None else None for t in vars(state).values()))
            self._cache = (key, state)
        return state

    def deform(self, c: Canonical, params: dict[str, torch.Tensor],
               normals: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Deformed points (B, N, 3, posed head space, metres) and unit normals (B, N, 3) there
        (None with ``normals`` False: ``c.grad`` and ``c.tangents`` are then not read).

        With u = M_c^-1 x_o + (psi - psi_c) E + (p - p_c) P the blendshaped rest point and
        x_d = R u + t (R, t: the blended frame transform), the Jacobian along a direction of q is
        dx_d = R du + dR u + dt, du = R_c^-1 (dx_o - dR_c r0 - dt_c) + dh G^T (r0 = R_c^-1 (x_o - t_c)),
        every d from the deformer's forward-mode tangents (dh, dW, dO): exact, and tested
        against finite differences."""
        B = params["translation"].shape[0]
        A, p = self.head.skinning_transforms(self.shape.expand(B, -1), params["expression"],
                                             {k: params[k] for k in POSE_ARGS})
        A = self._with_static_bone(A)[:, :, :3]  # (B, J+1, 3, 4)
        A_c = self.canonical_transforms[:, :3]  # (J+1, 3, 4)
        G, g = self.deformer.blend_matrices(params["expression"] - self.canonical_expression,
                                            p - self.canonical_pose_feature)  # (B, 3, width), (B, 3)
        x_o = c.q * SCALE + self.centre + c.O
        M_c = torch.einsum("nj,jab->nab", c.W, A_c)
        R_c_inv = torch.linalg.inv(M_c[..., :3])
        r0 = torch.einsum("nab,nb->na", R_c_inv, x_o - M_c[..., 3])
        u = r0 + torch.einsum("nw,bcw->bnc", c.h, G) + g[:, None]  # (B, N, 3)
        M = torch.einsum("nj,bjac->bnac", c.W, A)  # (B, N, 3, 4)
        x_d = torch.einsum("bnac,bnc->bna", M[..., :3], u) + M[..., 3]
        if not normals:
            return x_d, None
        n_c = torch.nn.functional.normalize(c.grad, dim=-1)
        if c.tangents is None:  # normals by the blended rotation alone (the ablation)
            n = torch.einsum("bnac,nc->bna", M[..., :3], torch.einsum("nab,nb->na", R_c_inv, n_c))
            return x_d, torch.nn.functional.normalize(n, dim=-1)
        dh, dW, dO = c.tangents
        eye = torch.eye(3, dtype=x_o.dtype, device=x_o.device)
        dx_o = SCALE * eye[:, None, :] + dO  # (3, N, 3)
        dM_c = torch.einsum("knj,jab->knab", dW, A_c)
        dr0 = torch.einsum("nab,knb->kna", R_c_inv, dx_o - dM_c[..., 3] - torch.einsum("knab,nb->kna", dM_c[..., :3], r0))
        du = dr0[None] + torch.einsum("knw,bcw->bknc", dh, G)  # (B, 3, N, 3)
        dM = torch.einsum("knj,bjac->bknac", dW, A)  # (B, 3, N, 3, 4)
        dx = (torch.einsum("bnac,bknc->bkna", M[..., :3], du) + torch.einsum("bknac,bnc->bkna", dM[..., :3], u)
              + dM[..., 3])
        jac = dx.permute(0, 2, 3, 1)  # (B, N, 3 out, 3 in): dx_d / dq
        n = torch.linalg.solve(jac.transpose(-1, -2), n_c.expand(B, -1, -1)[..., None])[..., 0]  # J^-T n_c
        return x_d, torch.nn.functional.normalize(n, dim=-1)

    def learned_shading(self, normals: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) shading in [0, 2] of the shading MLP (sigmoid x 2, the authors' code) at
        normals (B, N, 3)."""
        return self.shading_net(normals) * 2

    def mouth_gate(self, c: Canonical) -> torch.Tensor:
        """(N,) in (0, 1]: exp(-(d / mouth_albedo_radius)^2), d the distance (m) of each point's x_o
        (the canonical, jaw-open pose) to the nearest of the canonical inner-lip ring and its
        centroid: 1 on the lips and in the opening, 0.02 two radii away."""
        x_o = (c.q * SCALE + self.centre + c.O).detach()
        mouth = self.canonical_mouth
        ring = torch.cat([mouth, mouth.mean(0, keepdim=True)]).to(x_o)
        d = torch.cdist(x_o, ring).min(1).values
        return torch.exp(-(d / self.mouth_albedo_radius) ** 2)

    def frame_albedo(self, c: Canonical, params: dict[str, torch.Tensor] | None, B: int) -> torch.Tensor:
        """(B, N, 3) albedo in [0, 1] at frames ``params``: the canonical albedo, plus near the mouth
        the mouth-albedo network's change at the frame's expression and jaw (deviation 19) where
        that network exists and ``params`` are given."""
        albedo = c.albedo.expand(B, -1, -1)
        if self.mouth_albedo_net is None or params is None:
            return albedo
        gate = self.mouth_gate(c)
        rows = torch.nonzero(gate > 1e-3)[:, 0]  # the network runs on the points near the mouth only
        cond = torch.cat([params["expression"] - self.canonical_expression, params["jaw_pose"]], -1).to(albedo)
        delta = self.mouth_albedo_net(c.q[rows].detach(), cond) * gate[rows, None]
        return (albedo.clone().index_add(1, rows, delta)).clamp(0, 1)

    def colours(self, c: Canonical, normals: torch.Tensor, light: dict | None = None,
                albedo: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(colour, shading), each (B, N, 3) in [0, 1], at deformed normals (B, N, 3). ``light``:
        None (the learned shading), {"rotate": (3, 3)} (the learned shading of rotated normals: a
        light-direction change), {"direction": (3,)} (Lambert) or {"sh": (9, 3)} (2nd-order SH),
        the latter two with the learned albedo under the clip's mean light (a uniform light of 1
        keeps the clip's brightness); directions in the posed head frame. ``albedo``: (B, N, 3) the
        frames' albedo (:meth:`frame_albedo`); None: the canonical one."""
        albedo = c.albedo.expand(normals.shape[0], -1, -1) if albedo is None else albedo
        if self.colour_net is not None:  # entangled colour (the ablation): one MLP of albedo features and normal
            colour = self.colour_net(torch.cat([normals, albedo], -1))
            return colour, torch.ones_like(colour)
        if light is None or "rotate" in light:
            n = normals if light is None else normals @ light["rotate"].to(normals).T
            shading = self.learned_shading(n)
            return (albedo * shading).clamp(0, 1), shading
        # a light of the user's replaces the learned shading, relative to the clip's light: the
        # learned shading's mean over the points (per channel) goes into the albedo first, so a
        # uniform light of irradiance 1 keeps the clip's mean brightness and colour. a ∘ s is
        # ambiguous up to a per-channel factor, and the shading MLP takes the skin's tint and
        # brightness for its own once the normals are right (docs/pointavatar.md, relighting)
        tint = self.learned_shading(normals).mean(1, keepdim=True)
        albedo = albedo * tint
        if "direction" in light:
            shading = lambert(normals, torch.ones_like(albedo), light["direction"], ambient=light.get("ambient", 0.3))
        else:
            shading = sh_shading(normals, light["sh"].to(normals)).clamp(min=0)
        return (albedo * shading).clamp(0, 1), shading

    def landmarks(self, params: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """(B, L, 3) camera-space landmarks of the head model at the frame parameters ``params``
        (the head model's own deformation, not the points'); None for a model without any."""
        B = params["translation"].shape[0]
        out = self.head(shape=self.shape.expand(B, -1), **{k: params[k] for k in FRAME_KEYS if k != "translation"})
        return None if out.landmarks is None else head_to_camera(out.landmarks, params["translation"])

    def own_landmarks(self, params: dict[str, torch.Tensor], c: Canonical | None = None) -> torch.Tensor | None:
        """(B, L, 3) camera-space landmarks carried by the avatar's own deformation: the points x_c
        whose x_o = x_c + O(x_c) are the canonical head model's landmarks (jaw-open pose), deformed
        by the deformer's blendshapes and skinning exactly as cloud points there are, so they move
        with what the avatar draws rather than with the bare head model (:meth:`landmarks`).
        Differentiable in the frame parameters and the deformer; None without landmarks. ``c``:
        :meth:`landmark_canonical` when the caller has it already."""
        if len(self.canonical_landmarks) == 0:
            return None
        x_d, _ = self.deform(self.landmark_canonical() if c is None else c, params, normals=False)
        return head_to_camera(x_d, params["translation"])

    def landmark_canonical(self, iterations: int = 8) -> Canonical:
        """The deformer's outputs at the canonical landmarks' points (:meth:`own_landmarks`): q
        solves x_o(q) = q SCALE + centre + O(q) = landmark by fixed-point iteration (the offset is
        smooth and a few cm at most: 8 iterations leave under a micrometre on trained avatars), then
        h and W there with gradients. O is the constant that makes x_o the landmark exactly: q is re-solved at
        every call, so a gradient through O would push the cloud's offsets near the landmarks
        every step and never be satisfied. Only ``q``, ``h``, ``W`` and ``O`` are meaningful."""
        target = self.canonical_landmarks
        q = (target - self.centre) / SCALE
        with torch.no_grad():
            for _ in range(iterations):
                q = (target - self.centre - self.deformer(q)[2]) / SCALE
        h, W, _ = self.deformer(q)
        O = target - self.centre - q * SCALE
        nothing = q.new_zeros(q.shape)
        return Canonical(q, sdf=nothing[:, 0], grad=nothing, albedo=nothing, h=h, W=W, O=O, tangents=None)

    # ---- rendering --------------------------------------------------------------------------
    def posed(self, params: dict[str, torch.Tensor], training: bool = False):
        """(canonical state, camera-space points (B, N, 3), camera-space normals (B, N, 3),
        posed-head-space normals (B, N, 3))."""
        c = self.canonical(training)
        x_d, n_d = self.deform(c, params)
        flip = x_d.new_tensor(FLIP)
        return c, head_to_camera(x_d, params["translation"]), n_d * flip, n_d

    def render(self, params, cameras: Cameras, background: float = 1.0, normals: bool = False,
               light: dict | None = None, layers: bool = False, hole_filling: bool | None = None,
               training: bool = False) -> PointRender:
        c, pts, n_cam, n_d = self.posed(params, training)
        albedo = self.frame_albedo(c, params, n_d.shape[0])
        colour, shading = self.colours(c, n_d, light, albedo)
        features = [colour]
        if normals:
            features.append(n_cam)
        if layers:
            features += [albedo, shading.clamp(0, 2) / 2]
        depth = cameras.world_to_camera(pts)[..., 2]
        radius_px = cameras.K[:, 0, 0, None] * self.radius / depth.clamp(min=1e-3)
        img = self.splat(cameras, pts, torch.cat(features, -1), radius_px, n_cam)
        f, mask = img.features, img.mask
        if hole_filling if hole_filling is not None else (self.hole_filling and not training):
            f, mask = fill_holes(f, mask)
        rgb = f[..., :3] + (1 - mask[..., None]) * background
        out = PointRender(rgb, mask, max_weight=img.max_weight, front=img.front, canonical=c, points=pts,
                          point_normals=n_cam)
        i = 3
        if normals:
            out.normals = torch.nn.functional.normalize(f[..., i:i + 3], dim=-1) * (mask[..., None] > 1e-3)
            i += 3
        if layers:
            out.albedo = f[..., i:i + 3] + (1 - mask[..., None]) * background
            out.shading = f[..., i + 3:i + 6] + (1 - mask[..., None]) * background
        return out

    def geometry(self, params) -> Geometry:
        """The posed points in camera space with their normals and radii, and their regions as a
        mesh avatar's template gives them: a point is a face (head) point when the canonical head
        model's vertex nearest its x_o is in the face region (in neither neck region, as the
        tracked head model's regions in :func:`headforge.metrics.benchmark.tracked_geometry`)."""
        from headforge.metrics.benchmark import scored_regions

        c, pts, n_cam, _ = self.posed(params)
        nearest = self.nearest_canonical_vertices(c.q * SCALE + self.centre + c.O).cpu().numpy()
        face, head = scored_regions({name: self.head.region(name).cpu() for name in self.head.region_names},
                                    self.head.num_vertices)
        as_mask = lambda m: torch.from_numpy(m[nearest]).to(pts.device)  # noqa: E731
        return Geometry(pts, normals=n_cam, radius=self.radius.expand(pts.shape[:2]), face_vertices=as_mask(face),
                        head_vertices=as_mask(head), surfel_min_cos=self.surfel_min_cos,
                        hole_filling=self.hole_filling)

    # ---- coarse to fine ---------------------------------------------------------------------
    def prune(self) -> int:
        """Drop the points not ``visible`` since the last prune (never composited with a weight
        above 0.5 and, unless ``prune_keeps_front`` is off, never the nearest on a pixel);
        returns how many. Every point invisible is an error (nothing would be left to train)."""
        keep = self.visible
        if not bool(keep.any()):
            raise HeadforgeError("every point of the avatar was pruned away: none was visible in the training frames "
                                 "(the tracked head is outside the images, or the masks are empty)")
        removed = int((~keep).sum())
        self.points = nn.Parameter(self.points.detach()[keep])
        self.visible = torch.zeros(self.n_points, dtype=torch.bool, device=keep.device)
        return removed

    def upsample(self, gen: torch.Generator, factor: float, spread: float) -> None:
        """Double the points by copies perturbed uniformly within +-``spread`` point radii per axis,
        and shrink the radius by ``factor`` (paper supp. 2.2: 0.75)."""
        p = self.points.detach()
        noise = (torch.rand(p.shape, generator=gen) * 2 - 1).to(p) * (spread * self.radius / SCALE)
        self.points = nn.Parameter(torch.cat([p, p + noise]))
        self.radius = self.radius * factor
        self.visible = torch.zeros(self.n_points, dtype=torch.bool, device=p.device)

    def seed_mouth(self, gen: torch.Generator, n: int) -> None:
        """Add ``n`` points inside the canonical (jaw-open) mouth: uniform over the inner-lip ring's
        fan about its centroid, pushed up to ``MOUTH_DEPTH`` back (-z, canonical head frame): the
        doublings' copies rarely enter that concavity (``mouth_seed``, off by default: measured no
        better, docs/pointavatar.md deviation 15). Nothing for a model without MediaPipe landmarks."""
        ring = self.canonical_mouth
        if n <= 0 or len(ring) == 0:
            return
        c = ring.mean(0)
        i = torch.randint(len(ring), (n,), generator=gen)
        u, v = torch.rand(n, generator=gen), torch.rand(n, generator=gen)
        outside = u + v > 1
        u, v = torch.where(outside, 1 - u, u), torch.where(outside, 1 - v, v)
        x = c + u[:, None] * (ring[i] - c) + v[:, None] * (ring[(i + 1) % len(ring)] - c)
        x[:, 2] -= torch.rand(n, generator=gen) * MOUTH_DEPTH  # backward: the canonical face looks toward +z
        p = self.points.detach()
        self.points = nn.Parameter(torch.cat([p, ((x - self.centre) / SCALE).to(p)]))
        self.visible = torch.zeros(self.n_points, dtype=torch.bool, device=p.device)

    def load_weights(self, state: dict[str, torch.Tensor]) -> None:
        n = state["points"].shape[0]
        device = self.points.device
        self.points = nn.Parameter(torch.zeros(n, 3, device=device))
        self.visible = torch.zeros(n, dtype=torch.bool, device=device)
        state = {"landmark_bias": torch.zeros_like(self.landmark_bias)} | state  # runs from before 2026-12-04
        self.load_state_dict(state)
        self._cache = None

    # ---- export -----------------------------------------------------------------------------
    def export_formats(self) -> tuple[str, ...]:
        return ("ply",)

    @torch.no_grad()
    def export(self, output: Path, fmt: str, frames: list[int] | None = None, texture_size: int = 512,
               clip=None) -> list[Path]:
        """PLY point clouds: ``canonical.ply`` (the head model's canonical pose x_o, normals by the
        canonical SDF) and ``frame_XXXXX.ply`` posed in camera space for ``frames`` (default: 0); each
        vertex with position (m), normal, albedo (uchar) and radius (m). With a driving ``clip``
        (:class:`headforge.avatars.base.Clip`) also the animated sequence ``sequence/XXXXX.ply``
        (posed, camera space, one file per clip frame at ``clip.fps``)."""
        if fmt != "ply":
            raise HeadforgeError(f"PointAvatar exports ply, not {fmt!r}")
        output.mkdir(parents=True, exist_ok=True)
        c = self.canonical(False)
        albedo = c.albedo
        x_o = c.q * SCALE + self.centre + c.O
        written = [output / "canonical.ply"]
        write_ply(written[0], x_o, torch.nn.functional.normalize(c.grad, dim=-1), albedo, self.radius)
        for f in frames if frames else [0]:
            params = self.frame_params(torch.tensor([f], device=self.points.device))
            _, pts, n_cam, _ = self.posed(params)
            path = output / f"frame_{f:05d}.ply"
            write_ply(path, pts[0], n_cam[0], albedo, self.radius)
            written.append(path)
        if clip is not None:
            (output / "sequence").mkdir(exist_ok=True)
            T = clip.sequence["translation"].shape[0]
            for t in range(T):
                params = {k: v[t:t + 1].to(self.points.device) for k, v in clip.sequence.items()}
                _, pts, n_cam, _ = self.posed(params)
                path = output / "sequence" / f"{t:05d}.ply"
                write_ply(path, pts[0], n_cam[0], albedo, self.radius)
                written.append(path)
        return written


def sphere_points(n: int, radius: float, gen: torch.Generator) -> torch.Tensor:
    """(n, 3) points uniformly on a sphere of ``radius`` (normalised units) about the origin."""
    p = torch.randn(n, 3, generator=gen)
    return p / p.norm(dim=1, keepdim=True) * radius


def fill_holes(features: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Supp. 2.3's post-process: the composited image on white eroded then dilated (3x3), which
    closes single-pixel white holes between sparse points; features (B, H, W, C) pre-multiplied,
    mask (B, H, W). Returns pre-multiplied features and mask again."""
    pool = torch.nn.functional.max_pool2d
    img = (features + (1 - mask[..., None])).permute(0, 3, 1, 2)
    # erosion of the image (min filter: dark points grow over white holes), then dilation; the mask
    # the other way round (a closing: its holes filled)
    eroded = -pool(-img, 3, 1, 1)
    opened = pool(eroded, 3, 1, 1)
    m = close_mask(mask)
    f = opened.permute(0, 2, 3, 1)
    return f - (1 - m[..., None]), m


def write_ply(path: Path, positions: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor,
              radius: torch.Tensor | float) -> None:
    """A binary little-endian PLY: x y z nx ny nz (float32) red green blue (uchar) radius (float32)."""
    pos = positions.detach().cpu().numpy().astype("<f4")
    nrm = normals.detach().cpu().numpy().astype("<f4")
    rgb = (albedo.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype("u1")
    rad = np.broadcast_to(np.asarray(torch.as_tensor(radius).cpu(), dtype="<f4"), (len(pos),))
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                      ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("radius", "<f4")])
    rows = np.empty(len(pos), dtype)
    for i, k in enumerate("xyz"):
        rows[k] = pos[:, i]
        rows["n" + k] = nrm[:, i]
    rows["red"], rows["green"], rows["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    rows["radius"] = rad
    header = ("ply\nformat binary_little_endian 1.0\ncomment headforge PointAvatar (metres)\n"
              f"element vertex {len(pos)}\n" + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
              + "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty float radius\nend_header\n")
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        f.write(header.encode())
        f.write(rows.tobytes())
    tmp.replace(path)


def initial_point_radius(n_points: int, sphere_radius: float) -> float:
    """World radius (m) at which ``n_points`` discs cover a sphere of ``sphere_radius`` (normalised
    units) about twice: 4 pi R^2 = n pi r^2 / 2."""
    return 2 * math.sqrt(2) * sphere_radius * SCALE / math.sqrt(n_points)
