"""PointAvatar as a platform method: energies (Eq. 2, 11), optimisers, the coarse-to-fine hooks
(prune every ``prune_every``, double every ``upsample_every`` iterations; both change the number
of parameters, so the engine rebuilds the optimisers) and the pictures after training.

Energies over the protocol's head region (``batch["region"]``, from the tracked head model): the
RGB L1 against the frame matted on white, the mask L1, the head-model regulariser (expression
blendshapes, pose correctives and skinning weights against the nearest canonical head-model
vertex's), the SDF data term at the points and the Eikonal term at the points and perturbed
copies; with ``--supervision gt`` (beyond the paper) an L1 of the splatted normals against the
GT normal maps (and, as an option off in both presets, one of each visible point's own normal
against the GT normal at its pixel). Per-frame fitting (``align`` / ``align_rgb``, test-time tracking) uses the RGB term only,
as the paper's test-time tracking does; with ``w_landmarks`` / ``w_eyelids`` > 0 (an option beyond
the paper, off in both presets: measured worse, docs/pointavatar.md) the fitting also pulls the head
model's landmarks, less the avatar's landmark bias, to the detections; with ``landmarks_through``
"avatar" it pulls the avatar's own landmarks (the canonical head model's, deformed as the points
are) instead, in training too, where the head-model regulariser also holds the deformer there.
"""

from __future__ import annotations

import torch

from headforge.avatars.base import Method, RowAdam, Stage
from headforge.avatars.pointavatar.config import PointAvatarConfig
from headforge.avatars.pointavatar.model import SCALE, PointAvatarModel
from headforge.avatars.registry import register
from headforge.avatars.supervision import eyelid_term, landmark_term, normal_abs_term, point_normal_term
from headforge.head.landmarks import FACE_OVAL, N_MEDIAPIPE
from headforge.metrics.protocol import matte_on_white
from headforge.render.camera import Cameras, project_points


def head_model_term(avatar: PointAvatarModel, c, config: PointAvatarConfig, *more) -> torch.Tensor:
    """lambda_e MSE(E, E^) + lambda_p MSE(P, P^) + lambda_w MSE(W, W^) (means over every element,
    as the authors' code), the targets from the nearest canonical head-model vertex of each
    point's x_o (IMavatar's pseudo ground truth; the static bone's target weight is 0), over the
    points of ``c`` and of any ``more`` canonical states (the avatar's own landmarks)."""
    q, h, W, O = (torch.cat([getattr(s, k) for s in (c, *more)]) for k in "qhWO")
    x_o = q * SCALE + avatar.centre + O
    nearest = avatar.nearest_canonical_vertices(x_o)
    E, P = avatar.deformer.blendshapes(h)
    e = (E - avatar.vertex_exprdirs[nearest]).pow(2).mean()
    p = (P - avatar.vertex_posedirs[nearest]).pow(2).mean()
    w = (W - avatar.vertex_weights[nearest]).pow(2).mean()
    return config.w_expr * e + config.w_pose * p + config.w_weights * w


def flame_factor(step: int, config: PointAvatarConfig) -> float:
    """The head-model regulariser's multiple at training step ``step``: halved at every
    ``flame_halving_every`` of the iterations, ``flame_halvings`` times (the authors' milestones)."""
    passed = int(step // (config.flame_halving_every * config.iterations))
    return 0.5 ** min(passed, config.flame_halvings)


def eikonal_term(avatar: PointAvatarModel, c, config: PointAvatarConfig, gen: torch.Generator | None = None) -> torch.Tensor:
    """(|grad SDF| - 1)^2 at (a subsample of) the points and as many uniformly perturbed copies
    (+-0.4 normalised units, the authors' +-0.25 in FLAME x 4 units)."""
    q, grad = c.q.detach(), c.grad
    n = config.eikonal_samples
    if 0 < n < len(q):
        rows = torch.randperm(len(q), generator=gen)[:n].to(q.device)
        q, grad = q[rows], grad[rows]
    noise = (torch.rand(q.shape, generator=gen).to(q) - 0.5) * 0.8
    _, grad_perturbed, _ = avatar.canonical_net.sdf_and_normal(q + noise, create_graph=True)
    g = torch.cat([grad, grad_perturbed])
    return (g.norm(dim=-1) - 1).pow(2).mean()


def landmark_terms(avatar: PointAvatarModel, params: dict, detected: torch.Tensor, K: torch.Tensor,
                   config: PointAvatarConfig, own_canonical=None) -> dict[str, torch.Tensor]:
    """Landmarks against ``detected`` (B, L, 2) pixels, and the eye opening (NHA's terms,
    :mod:`headforge.avatars.supervision`). ``landmarks_through`` "head_model": the head model's
    landmarks at the frame parameters, less the avatar's ``landmark_bias``; they steer the frame
    parameters only (the head model's landmarks do not depend on the networks). The bias is the
    offset the trained avatar's frames hold on the training frames (:func:`landmark_bias`): the
    points are not the head model, and a frame pulled onto the bare model's landmark fit leaves
    the avatar's own features behind. "avatar": the avatar's own landmarks
    (:meth:`PointAvatarModel.own_landmarks`, deformed as its points are), no bias; they steer
    the frame parameters and, in training, the deformer (``own_canonical``: its
    :meth:`PointAvatarModel.landmark_canonical` when the caller has it)."""
    own = config.landmarks_through == "avatar"
    lmk = avatar.own_landmarks(params, own_canonical) if own else avatar.landmarks(params)
    if lmk is None:
        return {}
    if not config.landmarks_oval and detected.shape[1] == N_MEDIAPIPE:
        # MediaPipe's face oval follows the 2D outline, the model's oval landmarks fixed surface
        # points: pinned to the outline they widen the cheeks (skipped as undetected)
        detected = detected.clone()
        detected[:, FACE_OVAL] = float("nan")
    proj, res = project_points(lmk, K), config.resolution
    if not own:
        n = min(proj.shape[1], avatar.landmark_bias.shape[0])
        proj = proj[:, :n] - avatar.landmark_bias[:n]
    out = {"landmarks": config.w_landmarks * landmark_term(proj, detected) / res * 10}
    if config.w_eyelids > 0 and min(proj.shape[1], detected.shape[1]) == N_MEDIAPIPE:
        out["eyelids"] = config.w_eyelids * eyelid_term(proj, detected) / res * 10
    return out


@torch.no_grad()
def landmark_bias(avatar: PointAvatarModel, data) -> torch.Tensor:
    """(L, 2) pixels: per landmark, the median over ``data``'s frames (the training frames) of the
    head model's projected landmarks at the avatar's frame parameters minus the detections."""
    offsets = []
    for rows in torch.arange(len(data)).split(64):
        batch = data.batch(rows)
        lmk = avatar.landmarks(avatar.frame_params(batch["index"]))
        n = min(lmk.shape[1], batch["landmarks"].shape[1])
        offsets.append(project_points(lmk, data.K)[:, :n] - batch["landmarks"][:, :n])
    bias = torch.cat(offsets).nanmedian(0).values
    return torch.nan_to_num(bias).to(avatar.landmark_bias)


def uses_landmarks(config: PointAvatarConfig) -> bool:
    return config.w_landmarks > 0 or config.w_eyelids > 0


def uses_landmark_bias(config: PointAvatarConfig) -> bool:
    return uses_landmarks(config) and config.landmarks_through == "head_model"


def uses_own_landmarks(config: PointAvatarConfig) -> bool:
    return uses_landmarks(config) and config.landmarks_through == "avatar"


def losses(avatar: PointAvatarModel, batch: dict, K: torch.Tensor, config: PointAvatarConfig, stage: str,
           params: dict | None = None) -> dict[str, torch.Tensor]:
    from headforge.metrics.image import ssim

    B = len(batch["index"])
    params = avatar.frame_params(batch["index"]) if params is None else params
    training = stage == "train"
    # ground truth (a synth subject's training frames with --supervision gt): its normal maps
    gt = batch.get("gt_known") if training and (config.w_normal_abs > 0 or config.w_normal_points > 0) else None
    gt = gt if gt is not None and bool(gt.any()) else None
    r = avatar.render(params, Cameras.at_origin(K, B, config.resolution), background=1.0, training=training,
                      hole_filling=False, normals=gt is not None and config.w_normal_abs > 0)
    region = batch["region"]
    w = region[..., None].float()
    target = matte_on_white(batch["image"], batch["mask"])
    out = {"rgb": config.w_rgb * ((r.rgb - target).abs() * w).sum() / w.sum().clamp(min=1) / 3}
    if not training:  # the frame fitting (test-time and alignment): beyond the paper, its landmark terms
        if uses_landmarks(config):
            out |= landmark_terms(avatar, params, batch["landmarks"], K, config)
        return out
    with torch.no_grad():
        seen = r.max_weight > 0.5
        avatar.visible |= (seen | r.front).any(0) if config.prune_keeps_front else seen.any(0)
    out["mask"] = config.w_mask * ((r.coverage - batch["mask"]).abs() * region).sum() / region.sum().clamp(min=1)
    if config.w_ssim > 0:
        out["ssim"] = config.w_ssim * (1 - ssim(r.rgb * w + (1 - w), target * w + (1 - w)).mean())
    if gt is not None:
        known = region & gt[:, None, None]
        if config.w_normal_abs > 0:
            out["normal_abs"] = config.w_normal_abs * normal_abs_term(r.normals, batch["gt_normals"], r.coverage > 0.5, known)
        if config.w_normal_points > 0:
            pixels = project_points(r.points, K)
            out["normal_points"] = config.w_normal_points * point_normal_term(
                pixels, r.point_normals, r.max_weight > 0.5, batch["gt_normals"], known)
    c = r.canonical
    more = ()
    if uses_own_landmarks(config) and len(avatar.canonical_landmarks):
        # the avatar's own landmarks train the deformer and the frames with the images; the
        # head-model regulariser holds the deformer there too
        more = (avatar.landmark_canonical(),)
        out |= landmark_terms(avatar, params, batch["landmarks"], K, config, more[0])
    out["flame"] = config.w_flame * flame_factor(int(avatar.train_steps), config) * head_model_term(avatar, c, config, *more)
    out["sdf"] = config.w_sdf * c.sdf.pow(2).mean()
    gen = torch.Generator().manual_seed(config.seed * 7919 + int(avatar.train_steps))
    avatar.train_steps += 1
    out["eikonal"] = config.w_eikonal * eikonal_term(avatar, c, config, gen)
    return out


@register
class PointAvatarMethod(Method):
    name = "pointavatar"
    Config = PointAvatarConfig

    def build(self, assets, config: PointAvatarConfig) -> PointAvatarModel:
        config.validate()
        rows = assets.rows("train")
        canonical_expression = assets.tracking["expression"][rows].float().mean(0)
        return PointAvatarModel(assets.head_data(), assets.tracking, canonical_expression, config)

    def stages(self, config: PointAvatarConfig) -> list[Stage]:
        refined = ("frames",) if config.refine_poses or config.refine_expression else ()
        return [Stage("train", config.iterations, ("networks", "points") + refined)]

    def optimisers(self, avatar: PointAvatarModel, config: PointAvatarConfig) -> dict:
        nets = [p for n, p in avatar.named_parameters() if not n.startswith(("frames.", "points"))]
        return {"networks": torch.optim.Adam(nets, lr=config.lr),
                "points": torch.optim.Adam([avatar.points], lr=config.lr_points),
                # the authors' SparseAdam (one rate for expression, poses and camera): SGD at
                # their rate left the frames where the tracker put them (docs/pointavatar.md, deviation 7).
                # Nothing refined: kept over every frame parameter, unstepped (stages), so that its
                # zero_grad still clears their gradients
                "frames": RowAdam([p for k, p in avatar.frames.items()
                                   if (config.refine_expression if k == "expression" else config.refine_poses)]
                                  or list(avatar.frames.values()), lr=config.lr_frames)}

    def losses(self, avatar, batch, K, config, stage, params=None):
        return losses(avatar, batch, K, config, stage, params)

    def after_iteration(self, ctx) -> bool:
        """Prune, then double, on their schedules (not after the last iteration)."""
        config, avatar, it = ctx.config, ctx.avatar, ctx.iteration
        if it >= config.iterations:
            return False
        changed = False
        if it % config.prune_every == 0:
            before = avatar.n_points
            removed = avatar.prune()
            ctx.state.setdefault("pruned", []).append([it, before, removed])
            changed = True
        if it % config.upsample_every == 0 and 2 * avatar.n_points <= config.max_points:
            avatar.upsample(torch.Generator().manual_seed(config.seed + it), config.radius_factor,
                            config.upsample_spread)
            avatar.seed_mouth(torch.Generator().manual_seed(config.seed + it + 1), config.mouth_seed)
            changed = True
        if changed:
            ctx.state.setdefault("points", []).append([it, avatar.n_points, float(avatar.radius)])
        if uses_landmark_bias(config) and it % config.val_every == 0:  # the validation's fitting uses it next
            avatar.landmark_bias.copy_(landmark_bias(avatar, ctx.train))
        return changed

    def after_training(self, ctx) -> dict:
        from headforge.avatars.pointavatar.pictures import write_pictures

        if uses_landmark_bias(ctx.config):  # before the held-out frames are fitted
            ctx.avatar.landmark_bias.copy_(landmark_bias(ctx.avatar, ctx.train))
        write_pictures(ctx.avatar, ctx.train, ctx.config, ctx.state, ctx.run)
        return {"n_points": ctx.avatar.n_points, "point_radius_mm": round(1000 * float(ctx.avatar.radius), 3)}

    def extra_scores(self, ctx) -> dict:
        from headforge.avatars.engine import score

        raw, _ = score(self, ctx.avatar, ctx.val, ctx.config, render_options={"hole_filling": False})
        return {"val_psnr_no_hole_filling": raw["psnr"], "val_psnr_head_no_hole_filling": raw["psnr_head"]}
