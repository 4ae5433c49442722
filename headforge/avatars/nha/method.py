"""Neural Head Avatars (Grassal et al., CVPR 2022) as a headforge method: energies, optimisers,
stages and hooks; the avatar itself is :class:`headforge.avatars.nha.model.NeuralHeadAvatar`.

Schedule (NHA Sec. 3.2 / App. A.3): geometry initialisation (landmarks, silhouette, regularisers;
G and the per-frame parameters), texture initialisation (photometric, geometry frozen), then
joint optimisation. Adam for the networks, SGD for the per-frame parameters.

Hooks: between the geometry and texture stages every training frame is aligned on its own (the
engine's per-frame fitting, ``align_steps`` steps against the silhouette, mask outline and
landmarks): training visits each frame only a few times, so without it the frames keep the
tracker's poses, whose few-pixel misfit of the outline was three quarters of the image error on
talking_bun. After training the avatar's edge softness is fitted to the training frames
(:func:`fit_matte`, :mod:`headforge.render.matte`): a segmenter's matte is soft over a few pixels
where a mesh edge is one; metrics.json gives the held-out PSNR with and without it.

Terms we can and cannot have on real video (no pretrained weights): NHA's normal term needs a
normal predictor and its perceptual term VGG -- both absent, so the normal term is off and a
weight-free SSIM term stands in for the perceptual one. NHA's semantic term becomes two regions:
the whole head against the foreground mask inside :func:`energy_area` (silhouette, plus the outline
chamfer of :func:`contour_term`), and the face against the face oval of the detected landmarks.
The photometric target is the matted frame (on white by its soft matte, as scored).
"""

from __future__ import annotations

import torch

from headforge.avatars.base import Method, Stage, frame_optimiser
from headforge.avatars.nha.config import NHAConfig
from headforge.avatars.registry import register
from headforge.avatars.supervision import eyelid_term, landmark_term, normal_abs_term
from headforge.errors import HeadforgeError
from headforge.metrics.protocol import matte_on_white
from headforge.render import mesh
from headforge.render.camera import Cameras, project_points

ALIGN_CHECKPOINT_FRAMES = 200  # training frames aligned between two checkpoints


def _above_neck(ring_indices: torch.Tensor, verts: torch.Tensor, K: torch.Tensor, res: int) -> torch.Tensor:
    """(B, H, W) bool: pixels above the neck cut, the mean row of the ring ``ring_indices`` of
    ``verts`` (B, V, 3) projected; below it the foreground mask shows neck and shoulders the
    avatar does not model."""
    ring = verts[:, ring_indices]
    y = project_points(ring, K)[..., 1]
    cut = y.mean(dim=1).detach()  # (B,) the ring's middle: the back of the neck projects higher
    rows = torch.arange(res, dtype=verts.dtype, device=verts.device)[None, :, None]
    return (rows < cut[:, None, None]).expand(-1, -1, res)


def energy_area(region: torch.Tensor, ring_indices: torch.Tensor, verts: torch.Tensor, K: torch.Tensor,
                res: int) -> torch.Tensor:
    """(B, H, W) bool: where the energies compare the avatar with the frame. The scoring
    protocol's head ``region`` (B, H, W) bool, from the tracked head model: it follows the
    head's pose, so a looking-down chin is trained as it is scored; together with the rows above
    the avatar's own open neck end (``ring_indices``, the template's ``train_ring``), which with
    the lower neck kept reach below NHA's cut to the chin's outline against the neck
    (docs/nha_table1.md). Until 2026-12-02 the rows alone: a looking-down frame's chin lay below
    them (docs/nha_figures.md)."""
    return region | _above_neck(ring_indices, verts, K, res)


def mask_outline(mask: torch.Tensor, area: torch.Tensor, max_points: int = 3000) -> list[torch.Tensor]:
    """Per frame, pixel coordinates (x, y) of the GT mask's outline inside ``area`` (B, H, W)."""
    m = mask > 0.5
    inner = m.clone()
    inner[:, 1:-1, 1:-1] = m[:, 1:-1, 1:-1] & m[:, :-2, 1:-1] & m[:, 2:, 1:-1] & m[:, 1:-1, :-2] & m[:, 1:-1, 2:]
    edge = m & ~inner & area
    out = []
    for b in range(len(m)):
        yx = torch.nonzero(edge[b]).float()
        if len(yx) > max_points:
            yx = yx[torch.linspace(0, len(yx) - 1, max_points, device=yx.device).long()]
        out.append(yx.flip(-1))
    return out


def outer_band(covered: torch.Tensor, width: int = 2) -> torch.Tensor:
    """(B, H, W) bool: pixels within ``width`` pixels of an uncovered one (``covered`` (B, H, W)
    bool, the rendered coverage) -- where the rendered outer silhouette can lie."""
    uncovered = (~covered).float()[:, None]
    return torch.nn.functional.max_pool2d(uncovered, 2 * width + 1, stride=1, padding=width)[:, 0] > 0


def contour_term(avatar, vertices: torch.Tensor, gt_mask: torch.Tensor, area: torch.Tensor, K: torch.Tensor,
                 res: int, covered: torch.Tensor | None = None) -> torch.Tensor:
    """Symmetric 2D chamfer (L1-like, in units of the image size) between the GT mask outline and
    the projected silhouette-rim vertices of the avatar. Unlike the antialiased silhouette, whose
    gradient lives in the one-pixel band at the rendered edge, it pulls the surface toward mask
    parts far away (hair, a bun) -- the role of NHA's soft-rasterised semantic term.

    ``covered`` (B, H, W) bool, the rendered coverage: rim vertices that project inside it (the
    flanks of the nose, a cheek in front of the hair, the far side of the head) are occluding
    contours within the silhouette or hidden, not part of its outline, and are left out --
    pulled to the mask outline they would bulge the face toward the hair."""
    rims = avatar.contour_points(vertices, K)
    outlines = mask_outline(gt_mask, area)
    band = outer_band(covered) if covered is not None else None
    terms = []
    for b, (rim, outline) in enumerate(zip(rims, outlines)):
        inside = (rim >= 0).all(1) & (rim < res).all(1)
        rim = rim[inside]
        if len(rim):  # rim points below the neck cut have no outline to match
            y, x = rim[:, 1].long(), rim[:, 0].long()
            keep = area[b, y, x] if band is None else area[b, y, x] & band[b, y, x]
            rim = rim[keep]
        if len(rim) == 0 or len(outline) == 0:
            continue
        d = torch.cdist(outline, rim)
        terms.append(d.min(1).values.mean() + d.min(0).values.mean())
    if not terms:
        return vertices.new_zeros(())
    return torch.stack(terms).mean() / res


def offset_terms(avatar, mm: torch.Tensor, config: NHAConfig) -> dict[str, torch.Tensor]:
    """The squared-offset penalties on (B, V, 3) offsets ``mm`` in millimetres: the face's
    (``w_offset_face``) and the inner surfaces' (``w_offset_inner``: eyeballs, eye cavities, mouth
    interior, which no silhouette or normal term reaches), each a mean over all vertices."""
    squared = (mm ** 2).sum(-1)
    return {"offset_face": config.w_offset_face * (squared * avatar.face_vertices).mean(),
            "offset_inner": config.w_offset_inner * (squared * avatar.inner_vertices).mean()}


def losses(avatar, batch: dict, K: torch.Tensor, config: NHAConfig, stage: str,
           params: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
    """Weighted energy terms of one batch. ``stage``: geometry, texture or joint (the training
    stages), align (data terms that fit per-frame parameters: landmarks, silhouette, outline,
    prior) or align_rgb (align plus the photometric terms). ``params``: the batch's per-frame
    parameters (default: the avatar's own rows for ``batch["index"]``)."""
    from headforge.metrics.image import ssim

    res = config.resolution
    B = len(batch["index"])
    params = avatar.frame_params(batch["index"]) if params is None else params
    photometric = stage in ("texture", "joint", "align_rgb")
    semantic = config.w_semantic > 0 and stage != "texture"
    # ground truth (a synth subject's training frames with --supervision gt): NHA's normal and
    # semantic terms on the GT maps; a real clip has neither (no pretrained predictor here)
    gt = batch.get("gt_known")
    gt = gt if gt is not None and stage != "texture" and bool(gt.any()) else None
    r = avatar.render(params, Cameras.at_origin(K, B, res), background=1.0, texture=photometric, face_region=semantic,
                      matte=False, normals=gt is not None and (config.w_normal > 0 or config.w_normal_abs > 0),
                      classes=gt is not None and config.w_classes > 0)
    area = energy_area(batch["region"], avatar.train_ring, r.vertices, K, res)
    gt_mask = batch["mask"] * area
    out = {}
    # landmarks (L1, pixels / resolution), detections that exist only
    lmk = batch["landmarks"]
    if r.landmarks is not None:
        proj = project_points(r.landmarks, K)
        out["landmarks"] = config.w_landmarks * landmark_term(proj, lmk) / res * 10
        if config.w_eyelids > 0 and min(proj.shape[1], lmk.shape[1]) == 478:
            out["eyelids"] = config.w_eyelids * eyelid_term(proj, lmk) / res * 10
    out["silhouette"] = config.w_silhouette * ((r.coverage - gt_mask).abs() * area).mean()
    if semantic and r.face_region is not None:
        # NHA's semantic term for the one region we can segment without a face parser: the face oval
        known = batch["face_known"][:, None, None]
        out["semantic"] = config.w_semantic * ((r.face_region - batch["face_region"]).abs() * area * known).mean()
    if gt is not None:
        known = area & gt[:, None, None]
        if config.w_normal > 0:
            out["normal"] = config.w_normal * normal_term(r.normals, batch["gt_normals"], r.fragments.face_id >= 0, known)
        if config.w_normal_abs > 0:
            out["normal_abs"] = config.w_normal_abs * normal_abs_term(r.normals, batch["gt_normals"], r.fragments.face_id >= 0, known)
        if config.w_classes > 0:
            out["classes"] = config.w_classes * semantic_gt_term(r.classes, batch["gt_labels"], known)
    if config.w_contour > 0:
        out["contour"] = config.w_contour * contour_term(avatar, r.vertices, gt_mask, area, K, res, r.fragments.face_id >= 0)
    if photometric:
        # The target is the matted frame (on white, as evaluated): where the matte is soft (hair
        # strands, a segmenter unsure of a bun) the texture learns the colour the frame shows.
        inter = (r.coverage.detach() > 0.5) & (batch["mask"] > 0.5) & area
        w = inter[..., None].float()
        matted = matte_on_white(batch["image"], batch["mask"])
        out["rgb"] = config.w_rgb * ((r.rgb - matted).abs() * w).sum() / w.sum().clamp(min=1) / 3
        gt_comp = matted * w + (1 - w)
        pred_comp = r.rgb * w + (1 - w)
        out["ssim"] = config.w_ssim * (1 - ssim(pred_comp, gt_comp).mean())
        if r.albedo is not None and config.w_albedo_tv > 0:
            out["albedo_tv"] = config.w_albedo_tv * albedo_tv(r.albedo, inter)
    if stage != "texture":
        out["prior"] = config.w_prior * (params["expression"].pow(2).mean() + avatar.shape.pow(2).mean()
                                         + 10 * sum(params[k].pow(2).mean() for k in ("neck_pose", "jaw_pose")))
    if stage in ("geometry", "joint"):
        mm = 1000 * r.offsets  # regularisers in millimetres
        out["laplacian"] = config.w_laplacian * avatar.laplacian_term(mm, stage)
        out |= offset_terms(avatar, mm, config)
        out["edge"] = config.w_edge * avatar.edge_term(r.offsets + avatar.head.v_template)
        if B > 1:  # surface consistency between the frames of the batch (random pairs)
            out["surface"] = config.w_surface * (r.offsets[0] - r.offsets[1]).abs().mean()
    return out


# synth's labels (headforge.bench.synthetic.LABELS) of each of SEMANTIC_CLASSES; the mouth's
# inside (5) is in no class and left out, body (7) and background (0) are outside every class
GT_LABELS_OF_CLASS = {"skin": (1, 2, 6), "eyes": (4,), "hair": (3,)}
GT_UNSCORED_LABELS = (5,)


def image_laplacian(x: torch.Tensor) -> torch.Tensor:
    """(B, H, W, C) 4-neighbour image Laplacian of ``x`` (B, H, W, C); zero on the border rows
    and columns."""
    out = torch.zeros_like(x)
    inner = x[:, 1:-1, 1:-1]
    out[:, 1:-1, 1:-1] = x[:, :-2, 1:-1] + x[:, 2:, 1:-1] + x[:, 1:-1, :-2] + x[:, 1:-1, 2:] - 4 * inner
    return out


def with_neighbours(valid: torch.Tensor) -> torch.Tensor:
    """(B, H, W) bool: ``valid`` pixels whose four neighbours are valid too (where the Laplacian
    sees only valid values)."""
    out = torch.zeros_like(valid)
    out[:, 1:-1, 1:-1] = (valid[:, 1:-1, 1:-1] & valid[:, :-2, 1:-1] & valid[:, 2:, 1:-1]
                          & valid[:, 1:-1, :-2] & valid[:, 1:-1, 2:])
    return out


def normal_term(normals: torch.Tensor, gt_normals: torch.Tensor, covered: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """NHA's E_normal (Sec. 3.2): L1 between the image-space Laplacians of the rendered and the
    ground-truth camera-space normal maps (B, H, W, 3; ground truth of length < 0.5 off the
    subject), summed over the channels, mean over the pixels of ``area`` (B, H, W) bool where
    both maps are defined with their four neighbours (``covered``: the render's hard coverage).
    It matches detail (folds, the hair's relief), not the normals' absolute directions."""
    valid = with_neighbours(covered & (gt_normals.norm(dim=-1) > 0.5)) & area
    diff = (image_laplacian(normals) - image_laplacian(gt_normals)).abs().sum(-1)
    return (diff * valid).sum() / valid.sum().clamp(min=1)


def semantic_gt_term(classes: torch.Tensor, gt_labels: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """NHA's E_semantic (Sec. 3.2) against ground-truth labels: the soft XOR |S_k - S^_k| of the
    rendered coverage by each class (``classes`` (B, H, W, C), SEMANTIC_CLASSES) and the labels'
    region of it (``gt_labels`` (B, H, W) synth labels), summed over the classes, mean over the
    pixels of ``area`` (B, H, W) bool except the mouth's inside."""
    from headforge.avatars.nha.model import SEMANTIC_CLASSES

    target = torch.stack([torch.isin(gt_labels, torch.tensor(GT_LABELS_OF_CLASS[name], device=gt_labels.device))
                          for name in SEMANTIC_CLASSES], -1).to(classes.dtype)
    scored = area & ~torch.isin(gt_labels, torch.tensor(GT_UNSCORED_LABELS, device=gt_labels.device))
    return ((classes - target).abs().sum(-1) * scored).sum() / scored.sum().clamp(min=1)


@torch.no_grad()
def classes_from_labels(avatar, data, config: NHAConfig, frames: int = 32) -> torch.Tensor:
    """(V, C) one-hot class of each template vertex in SEMANTIC_CLASSES, voted from the ground-truth
    labels (``gt_labels``) of ``frames`` evenly spaced training frames of ``data`` at the avatar's
    current frame parameters: every covered pixel's label votes for the three corners of the
    triangle it sees, by barycentric weight. Vertices no labelled pixel sees keep the template's
    class; the mouth's inside stays in no class. The subject's hairline is then the mesh's
    (a fringe over the template's forehead, hair over its ears), so the semantic term aligns regions
    the offsets can reach instead of asking the surface to slide across the head."""
    from headforge.avatars.nha.model import SEMANTIC_CLASSES

    table = avatar.semantic_classes().clone()
    V, C = table.shape
    votes = torch.zeros(V, C + 1)  # the last column: labels in no class (the mouth's inside)
    faces = avatar.head.faces
    lut = torch.full((256,), -1, dtype=torch.long)
    for c, name in enumerate(SEMANTIC_CLASSES):
        lut[list(GT_LABELS_OF_CLASS[name])] = c
    lut[list(GT_UNSCORED_LABELS)] = C
    rows = torch.linspace(0, len(data) - 1, min(frames, len(data))).long()
    for chunk in rows.split(config.batch):
        batch = data.batch(chunk)
        if "gt_labels" not in batch:
            raise HeadforgeError("semantic_classes=labels needs ground-truth labels (--supervision gt on a synth subject)")
        verts, _, _ = avatar.pose(avatar.frame_params(batch["index"]))
        cameras = Cameras.at_origin(data.K, len(chunk), config.resolution)
        frags = mesh.rasterize(cameras, verts, faces)
        bary = mesh.barycentrics(frags, cameras, verts, faces)
        device = verts.device
        hit = (frags.face_id >= 0) & batch["gt_known"][:, None, None].to(device)
        label = lut.to(device)[batch["gt_labels"].to(device)[hit]]
        keep = label >= 0
        corners = faces[frags.face_id[hit]][keep].reshape(-1)  # (N * 3,)
        weight = bary[hit][keep].reshape(-1)
        votes.index_put_((corners.cpu(), label[keep].repeat_interleave(3).cpu()), weight.cpu().float(), accumulate=True)
    seen = votes.sum(1) > 0.5
    mouth = table.sum(1) == 0
    winner = votes.argmax(1)
    new = torch.nn.functional.one_hot(winner.clamp(max=C - 1), C).float()
    new[winner == C] = 0.0
    update = seen & ~mouth
    table[update] = new[update]
    return table


def albedo_tv(albedo: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
    """Mean L1 difference (per channel) of ``albedo`` (B, H, W, 3) between horizontally and
    vertically neighbouring pixels that are both ``inside`` (B, H, W) bool. Shading baked into the
    albedo varies smoothly and costs its full variation here; the piecewise-constant albedo of
    hair, skin and lips costs only its edges."""
    total, count = albedo.new_zeros(()), 0
    for a, b, ia, ib in ((albedo[:, :, 1:], albedo[:, :, :-1], inside[:, :, 1:], inside[:, :, :-1]),
                         (albedo[:, 1:], albedo[:, :-1], inside[:, 1:], inside[:, :-1])):
        both = (ia & ib)[..., None]
        total = total + ((a - b).abs() * both).sum()
        count += int(both.sum())
    return total / max(count, 1) / 3


def optimisers(avatar, config: NHAConfig) -> dict:
    frames = frame_optimiser(avatar, config.lr_frames)
    geometry = torch.optim.Adam([{"params": avatar.geometry_net.parameters(), "lr": config.lr_geometry},
                                 {"params": [avatar.shape], "lr": config.lr_shape}])
    grids = ("grid", "mouth_grid")
    texture = torch.optim.Adam([{"params": [p for n, p in avatar.texture_net.named_parameters() if n not in grids],
                                 "lr": config.lr_texture, "weight_decay": config.tex_weight_decay},
                                {"params": [getattr(avatar.texture_net, n) for n in grids], "lr": config.lr_grid}]
                               + ([{"params": [avatar.sh], "lr": config.lr_texture * 10}] if avatar.sh is not None else []))
    return {"frames": frames, "geometry": geometry, "texture": texture}


def build_avatar(assets, config: NHAConfig):
    from headforge.avatars.nha.model import NeuralHeadAvatar, build_template

    config.check()
    if config.stage_epochs:
        want = config.epoch_iterations(len(assets.rows("train")))
        if want != (config.geometry_iters, config.texture_iters, config.joint_iters):
            raise HeadforgeError(f"stage_epochs {config.stage_epochs} make {want} iterations on this dataset, the config has "
                                 f"{(config.geometry_iters, config.texture_iters, config.joint_iters)}: call "
                                 f"config.schedule_for(training frames) first (headforge fit does)")
    template = build_template(assets.head_data(), config.subdivide, config.remove_lower_neck, config.close_mouth,
                              config.laplacian_regions == "table3")
    return NeuralHeadAvatar(template, assets.tracking, config)


@torch.no_grad()
def fit_matte(avatar, data, config: NHAConfig, frames: int = 32) -> tuple[float, list]:
    """Fit the avatar's soft-matte sigma (:mod:`headforge.render.matte`) to ``frames`` evenly
    spaced frames of ``data`` (training frames, with their fitted parameters): the edge width
    whose matted renders best match the matted frames inside the protocol's head region. Sets
    ``avatar.matte_sigma``; returns (sigma px, [(sigma, mse), ...])."""
    from headforge.metrics.protocol import composite
    from headforge.render.matte import fit_sigma

    rows = torch.linspace(0, len(data) - 1, min(frames, len(data))).long()
    rgb, cov, target, weight = [], [], [], []
    for chunk in rows.split(4 * config.batch):
        batch = data.batch(chunk)
        r = avatar.render(avatar.frame_params(batch["index"]), Cameras.at_origin(data.K, len(chunk), config.resolution),
                          background=1.0, matte=False)
        _, gt = composite(r.rgb, batch["image"], batch["mask"], batch["region"])
        rgb.append(r.rgb), cov.append(r.coverage), target.append(gt), weight.append(batch["region"])
    sigma, scores = fit_sigma(torch.cat(rgb), torch.cat(cov), torch.cat(target), torch.cat(weight))
    avatar.matte_sigma.fill_(sigma)
    avatar.matte_resolution.fill_(config.resolution)
    return sigma, scores


def held_back(config: NHAConfig, train_frames: int) -> torch.Tensor:
    """Positions (in the training frames) of the ``early_stop_frames`` frames held back from the
    end of the training range for the early stop: never trained on, never the scored split."""
    k = config.early_stop_frames
    if k * 2 > train_frames:
        raise HeadforgeError(f"early_stop_frames {k} needs at least {2 * k} training frames, the dataset has {train_frames}")
    return torch.arange(train_frames - k, train_frames)


@register
class NHAMethod(Method):
    name = "nha"
    Config = NHAConfig

    def build(self, assets, config: NHAConfig):
        return build_avatar(assets, config)

    def stages(self, config: NHAConfig) -> list[Stage]:
        return [Stage("geometry", config.geometry_iters, ("frames", "geometry")),
                Stage("texture", config.texture_iters, ("texture",)),
                Stage("joint", config.joint_iters, ("frames", "geometry", "texture"))]

    def optimisers(self, avatar, config: NHAConfig) -> dict:
        return optimisers(avatar, config)

    def losses(self, avatar, batch, K, config, stage, params=None):
        if config.early_stop_frames and stage in ("geometry", "texture", "joint"):
            batch = self._without_held_back(batch, config)
        return losses(avatar, batch, K, config, stage, params)

    def _without_held_back(self, batch: dict, config: NHAConfig) -> dict:
        """The training batch with each early-stop frame (:func:`held_back`) replaced by the frame
        ``early_stop_frames`` positions before it: those frames are never trained on."""
        train = self._train
        pos = (batch["index"][:, None] == train.index[None, :]).float().argmax(1)
        held = pos >= len(train) - config.early_stop_frames
        if not held.any():
            return batch
        return train.batch(torch.where(held, pos - config.early_stop_frames, pos).cpu())

    def before_iteration(self, ctx) -> None:
        """After the geometry stage: align every training frame on its own, checkpointing every
        ALIGN_CHECKPOINT_FRAMES frames ("aligned" in the run's state)."""
        config, train = ctx.config, ctx.train
        if config.semantic_classes == "labels" and "gt_known" in train.per_frame and not getattr(self, "_classes_set", False):
            self._set_subject_classes(ctx)
        if config.early_stop_frames:
            held_back(config, len(train))  # a one-line error for too short a training range
            self._train = train  # the training batches swap the held-back frames out (losses)
        aligned = ctx.state.get("aligned", 0)
        if ctx.iteration != config.geometry_iters or config.align_steps <= 0 or aligned >= len(train):
            return
        ctx.log(f"aligning training frames {aligned}..{len(train)} on their own ({config.align_steps} steps each)")
        for chunk in torch.arange(aligned, len(train)).split(ALIGN_CHECKPOINT_FRAMES):
            ctx.fit_frames(train, config.align_steps, rows=chunk)
            ctx.state["aligned"] = int(chunk[-1]) + 1
            ctx.checkpoint()
            ctx.log(f"aligned {ctx.state['aligned']}/{len(train)} training frames")

    def _set_subject_classes(self, ctx) -> None:
        """The avatar's semantic classes voted from the training frames' GT labels
        (:func:`classes_from_labels`) at the first iteration; kept in the run's state (one class
        index per vertex, -1: none) so that a resumed run uses the same table."""
        from headforge.avatars.nha.model import SEMANTIC_CLASSES

        C = len(SEMANTIC_CLASSES)
        if "semantic_classes" not in ctx.state:
            table = classes_from_labels(ctx.avatar, ctx.train, ctx.config)
            index = torch.where(table.sum(1) > 0, table.argmax(1), -1)
            ctx.state["semantic_classes"] = index.tolist()
            before = ctx.avatar.semantic_classes()
            moved = int((table != before).any(1).sum())
            ctx.log(f"semantic classes from the GT labels: {moved} of {len(index)} vertices change class "
                    f"({', '.join(f'{n} {int((index == c).sum())}' for c, n in enumerate(SEMANTIC_CLASSES))})")
        index = torch.tensor(ctx.state["semantic_classes"])
        table = torch.zeros(len(index), C)
        table[index >= 0] = torch.nn.functional.one_hot(index[index >= 0], C).float()
        ctx.avatar.set_semantic_classes(table)
        self._classes_set = True

    def after_iteration(self, ctx) -> bool:
        """Early stop (App. A.3, ``early_stop_frames`` > 0): every ``early_stop_every`` joint
        iterations, the held-back frames' (:func:`held_back`) L1 + (1 - SSIM) after the in-training
        validation's fitting (``val_tto_steps``; no VGG for the paper's perceptual loss); after
        ``early_stop_patience`` checks without a new best the joint stage ends (the engine's loop
        ends when the iteration reaches the total). State: "early_stop" in the run's state."""
        from headforge import distributed
        from headforge.avatars.engine import validate

        config = ctx.config
        done = ctx.iteration - config.geometry_iters - config.texture_iters
        if not config.early_stop_frames or done <= 0 or done % config.early_stop_every or ctx.iteration >= config.total_iters:
            return False
        held = held_back(config, len(ctx.train))
        scores = validate(self, ctx.avatar, ctx.train.subset(held), config)
        loss = distributed.broadcast_object(None if scores is None else scores["l1"] + 1 - scores["ssim"])
        state = ctx.state.setdefault("early_stop", {"best": None, "since": 0, "checks": []})
        state["checks"].append([ctx.iteration, loss])
        if state["best"] is None or loss < state["best"]:
            state["best"], state["since"] = loss, 0
        else:
            state["since"] += 1
        ctx.log(f"early stop check at {ctx.iteration}: held-back L1 + (1 - SSIM) {loss:.4f} (best {state['best']:.4f})")
        if state["since"] >= config.early_stop_patience:
            state["stopped_at"] = ctx.iteration
            ctx.log(f"early stop: the held-back frames' loss did not improve in {state['since']} checks; "
                    f"the joint stage ends at iteration {ctx.iteration} of {config.total_iters}")
            ctx.iteration = config.total_iters
        return False

    def after_training(self, ctx) -> dict:
        sigma, _ = fit_matte(ctx.avatar, ctx.train, ctx.config)
        ctx.log(f"soft matte: edge sigma {sigma:.2f} px fitted to the training frames")
        stopped = ctx.state.get("early_stop", {}).get("stopped_at")
        return {"matte_sigma_px": sigma} | ({"early_stop_iteration": stopped} if stopped else {})

    def extra_scores(self, ctx) -> dict:
        from headforge.avatars.engine import score

        hard, _ = score(self, ctx.avatar, ctx.val, ctx.config, render_options={"matte": False})
        return {"val_psnr_hard_edge": hard["psnr"]}

    def render_for_scoring(self, avatar, params, cameras, matte: bool = True):
        return avatar.render(params, cameras, background=1.0, matte=matte)
