"""The training engine every avatar method runs on: ``fit(METHOD, DATASET, RUN, config)``.

It owns the loop over the method's stages, the optimiser steps with the learning-rate decay,
checkpoints and exact resume (a killed run continues where it stopped, with the same random
batches), ``losses.csv``, ``val.csv``, ``progress.png``, in-training validation, per-frame
fitting of frame parameters (test-time fitting of the held-out frames, and the method's own
alignment steps), and the scoring of the held-out frames with the one protocol of
:mod:`headforge.metrics.protocol`. A method (:class:`~headforge.avatars.base.Method`) owns its
avatar, stages, optimisers, energies and hooks.

Per-frame fitting (:func:`fit_frames`): the networks frozen, each batch of frames gets its own
Adam on its expression, poses and translation for ``steps`` steps of the method's ``align``
energies, then ``photometric_steps`` of ``align_rgb``. Frames are independent once the networks
are frozen, so this is exact per-frame optimisation.

Over processes (``torchrun``, :mod:`headforge.distributed`): every rank draws the same global
batch and trains on its share (:func:`backward_step`), the gradients of all parameters are
averaged (the per-frame ones come from the rank holding the frame), so every rank keeps the
same weights; per-frame fitting deals its batches of frames out to the ranks and gathers the
results; rank 0 alone writes the run folder (checkpoints, logs, pictures, scores) and the
other ranks' hooks write into a scratch folder. One process runs exactly the code it ran before.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from headforge.avatars.base import Avatar, Method, Stage
from headforge.avatars.frames import FrameData
from headforge.avatars.run import RunAssets, load_weights, read_info, run_info, save_checkpoint
from headforge import distributed
from headforge.errors import HeadforgeError

TTO_CHECKPOINT_FRAMES = 64  # held-out frames test-time fitted between two checkpoints (~3 min on 2 CPU cores)
WORST_FRAMES = 6  # frames on the worst-frames sheet


def lr_factor(it: int, config) -> float:
    """Learning-rate multiple at iteration ``it``: 1 until ``lr_decay_start`` of the schedule,
    then a half cosine down to ``lr_final`` at the last iteration. Adam with a constant rate and
    batches of two frames ends on a noisy iterate; decaying settles it. A function of the
    iteration alone, so a resumed run gets the same rates."""
    start = config.lr_decay_start * config.total_iters
    if it < start:
        return 1.0
    progress = min(1.0, (it - start) / max(1.0, config.total_iters - start))
    return config.lr_final + (1 - config.lr_final) * 0.5 * (1 + math.cos(math.pi * progress))


def stage_at(stages: list[Stage], it: int) -> Stage:
    """The stage that iteration ``it`` belongs to."""
    end = 0
    for stage in stages:
        end += stage.iterations
        if it < end:
            return stage
    return stages[-1]


def fit_frames(method: Method, avatar: Avatar, data: FrameData, config, steps: int, photometric_steps: int = 0,
               rows: torch.Tensor | None = None) -> None:
    """Fit the frame parameters of ``data``'s frames (all, or positions ``rows``) with the
    avatar's own parameters frozen (see the module docstring)."""
    rows = torch.arange(len(data)) if rows is None else rows
    chunks = list(rows.split(4 * config.batch))
    mine = distributed.owned(len(chunks))  # all of them in one process
    was = [p.requires_grad for p in avatar.parameters()]
    avatar.requires_grad_(False)
    try:
        for chunk in (chunks[i] for i in mine):
            batch = data.batch(chunk)
            idx = batch["index"]
            params = {k: v.detach()[idx].clone().requires_grad_(True) for k, v in avatar.frames.items()}
            opt = torch.optim.Adam([{"params": [p], "lr": config.lr_align / 10 if k == "translation" else config.lr_align}
                                    for k, p in params.items()])
            for step in range(steps + photometric_steps):
                stage = "align" if step < steps else "align_rgb"
                loss = sum(method.losses(avatar, batch, data.K, config, stage, params).values())
                opt.zero_grad()
                loss.backward()
                opt.step()
            with torch.no_grad():
                for k, p in params.items():
                    avatar.frames[k][idx] = p.detach()
        if distributed.active():  # every rank gets the frames the others fitted
            own = set(mine)
            owner = torch.cat([torch.full((len(c),), i in own) for i, c in enumerate(chunks)])  # this rank's rows
            distributed.merge_rows(avatar.frames, data.index[torch.cat(chunks)], owner.to(data.index.device))
    finally:
        for p, flag in zip(avatar.parameters(), was):
            p.requires_grad_(flag)


def backward_step(method: Method, avatar: Avatar, optimisers: dict, data: FrameData, rows: torch.Tensor, config,
                  stage: str) -> tuple[torch.Tensor, dict]:
    """One training step's energies and gradients for the global batch ``rows`` (positions in
    ``data``): the optimisers' gradients zeroed, the method's ``losses`` of ``stage``, backward.
    Under torch.distributed each rank takes its share of ``rows`` and the gradients are averaged
    over the ranks (the single-process gradient of the global batch for energies that are means
    over its frames), boolean buffers OR-ed (:func:`headforge.distributed.combine_flags`), and the
    returned (loss, terms) are the ranks' means."""
    terms = method.losses(avatar, data.batch(distributed.shard(rows)), data.K, config, stage)
    loss = sum(terms.values())
    for o in optimisers.values():
        o.zero_grad()
    loss.backward()
    if distributed.active():
        distributed.average_gradients(list(avatar.parameters()))
        distributed.combine_flags(avatar)
        terms = distributed.mean_terms(terms)
        loss = sum(terms.values())
    return loss, terms


@torch.no_grad()
def score(method: Method, avatar: Avatar, data: FrameData, config, out_dir: Path | None = None, max_images: int = 6,
          landmarks: bool = False, render_options: dict | None = None, by_region: bool = False) -> tuple[dict, dict]:
    """The protocol's scores of ``data``'s frames at the avatar's frame parameters: (summary,
    per-frame arrays); with ``landmarks`` and ``by_region`` AKD per face region too. Writes up to
    ``max_images`` frame | avatar PNGs to ``out_dir``."""
    from headforge.metrics.protocol import composite, score_frames, summarise
    from headforge.render.camera import Cameras
    from headforge.render.io import write_png

    per_frame: dict[str, list] = {}
    saved = 0
    for rows in torch.arange(len(data)).split(config.batch):
        batch = data.batch(rows)
        cams = Cameras.at_origin(data.K, len(rows), config.resolution)
        r = method.render_for_scoring(avatar, avatar.frame_params(batch["index"]), cams, **(render_options or {}))
        s = score_frames(r.rgb, r.coverage, batch["image"], batch["mask"], batch["region"], batch["face_scored"],
                         landmarks=landmarks, by_region=by_region)
        for k, v in s.items():
            per_frame.setdefault(k, []).append(v)
        if out_dir is not None and saved < max_images:
            pred, gt = composite(r.rgb, batch["image"], batch["mask"], batch["region"])
            for b in range(min(len(rows), max_images - saved)):
                write_png(out_dir / f"{int(batch['index'][b]):05d}.png", torch.cat([gt[b], pred[b]], 1).clamp(0, 1))
                saved += 1
    arrays = {k: np.concatenate(v) for k, v in per_frame.items()}
    return summarise(arrays), arrays


def validate(method: Method, avatar: Avatar, data: FrameData, config, out_dir: Path | None = None) -> dict | None:
    """In-training validation: a short test-time fitting (``val_tto_steps``) of ``data``'s
    frames, the protocol's image scores, and the frames' parameters restored (it counts in the
    training time, so it does not take the final score's ``tto_steps``). Under torch.distributed
    the ranks share the fitting and rank 0 alone scores (None elsewhere)."""
    idx = data.index
    saved = {k: v.detach()[idx].clone() for k, v in avatar.frames.items()}
    try:
        fit_frames(method, avatar, data, config, config.val_tto_steps, config.tto_photometric_steps)
        return score(method, avatar, data, config, out_dir)[0] if distributed.is_main() else None
    finally:
        with torch.no_grad():
            for k, v in saved.items():
                avatar.frames[k][idx] = v


@dataclass
class TrainingContext:
    """What a method's hooks see of a running fit: the avatar, config, optimisers, the training
    and held-out frames, the resumable ``state`` (JSON; hooks keep their progress in it) and
    ``checkpoint()``."""

    run: Path
    method: Method
    avatar: Avatar
    config: object
    optimisers: dict
    train: FrameData
    val: FrameData
    state: dict
    log: object
    start: float
    iteration: int = 0

    def checkpoint(self) -> None:
        self.state.update(iteration=self.iteration, seconds=time.perf_counter() - self.start)
        if distributed.is_main():  # every rank holds the same weights and frames
            save_checkpoint(self.run, self.avatar, self.optimisers, self.state)

    def fit_frames(self, data: FrameData, steps: int, photometric_steps: int = 0, rows: torch.Tensor | None = None) -> None:
        fit_frames(self.method, self.avatar, data, self.config, steps, photometric_steps, rows)


def _resolve(method) -> Method:
    from headforge.avatars import registry

    return registry.get(method) if isinstance(method, str) else method


def fit(method: str | Method, dataset: str | Path, run: str | Path, config, log=print, progress=None,
        device: torch.device | str = "cpu") -> dict:
    """Train ``method`` (a registered name or instance) on ``dataset`` into the run folder
    ``run``, on ``device``; resumes from RUN's checkpoint when its settings and data match (also
    on another device: checkpoints are written from host copies). Returns metrics.json's figures.
    Inside a torch.distributed process group (torchrun) the ranks train together (module doc);
    ``run`` must then be on a file system every rank sees, and ``config.batch`` a multiple of
    the number of processes."""
    from headforge.metrics.protocol import TrackedHead

    method = _resolve(method)
    dataset, run = Path(dataset), Path(run)
    main = distributed.is_main()
    if distributed.active():
        if config.batch % distributed.world_size():
            raise HeadforgeError(f"batch {config.batch} cannot be split over {distributed.world_size()} processes: "
                                 f"--set batch=N with N a multiple of {distributed.world_size()}")
        if not main:
            log, progress = (lambda message: None), None
    torch.manual_seed(config.seed)
    assets = RunAssets.from_dataset(dataset)  # reads and checks the dataset first
    info = run_info(method.name, config, dataset, assets)
    resume = (run / "state.json").is_file()
    if resume or (run / "config.json").is_file():
        previous = read_info(run)
        if previous.get("method") != method.name:
            raise HeadforgeError(f"{run} holds a {previous.get('method')} run, not {method.name}: choose another -o or delete it")
        saved = previous | {"config": json.loads(json.dumps(method.Config.from_saved(previous.get("config", {}), run).__dict__))}
        if saved != info:
            raise HeadforgeError(f"{run} holds a run with other settings or data: choose another -o or delete it")
    avatar = method.build(assets, config)
    head = TrackedHead(assets.head_data(), assets.tracking["shape"])
    train = FrameData(dataset, "train", config.resolution, head, supervision=config.supervision).to(device)
    val_all = FrameData(dataset, "val", config.resolution, head).to(device)
    if train.detector_bias is not None:
        # trained on ground-truth landmarks, the held-out frames are fitted to detections: without
        # the detector's bias measured on the training frames their poses drift from the trained ones
        val_all.correct_detections(train.detector_bias)
    if main:
        run.mkdir(parents=True, exist_ok=True)
        if not resume:
            assets.save(run)
            (run / "run.json").write_text(json.dumps(info, indent=1))
        (run / "val").mkdir(exist_ok=True)
    avatar.to(device)
    state = {"iteration": 0, "seconds": 0.0}
    if resume:  # the weights first: a method's parameters may have changed size since build
        load_weights(avatar, run / "checkpoint.safetensors")
    optimisers = method.optimisers(avatar, config)
    if resume:
        for k, sd in torch.load(run / "optimisers.pt", map_location="cpu", weights_only=False).items():
            optimisers[k].load_state_dict(sd)
        state = json.loads((run / "state.json").read_text())
        for name in ("losses.csv", "val.csv"):  # rows a killed run wrote after its last checkpoint
            if main:
                _truncate_log(run / name, state["iteration"])
        log(f"resuming {run} at iteration {state['iteration']}")
    elif main:
        for name in ("losses.csv", "val.csv"):
            (run / name).unlink(missing_ok=True)
    distributed.barrier()  # the run folder is set up before any rank writes into it
    stages = method.stages(config)
    gen = torch.Generator().manual_seed(config.seed)
    for _ in range(state["iteration"]):  # a resumed run draws the batches the killed one would have
        torch.randperm(len(train), generator=gen)
    start = time.perf_counter() - state["seconds"]
    # ranks other than 0 give the hooks a scratch folder: only rank 0 writes into the run folder
    scratch = None if main else Path(tempfile.mkdtemp(prefix=f"headforge-rank{distributed.rank()}-"))
    ctx = TrainingContext(run if main else scratch, method, avatar, config, optimisers, train, val_all, state, log,
                          start, state["iteration"])
    try:
        metrics = _train_and_score(ctx, run, dataset, stages, gen, head, assets, device, progress)
    finally:
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
    return distributed.broadcast_object(metrics)


def _train_and_score(ctx: TrainingContext, run: Path, dataset: Path, stages: list[Stage], gen: torch.Generator, head,
                     assets: RunAssets, device, progress) -> dict:
    """:func:`fit`'s training loop, the held-out frames' fitting and the scores (rank 0 alone
    writes; ``run`` is the run folder, ``ctx.run`` a scratch folder on the other ranks)."""
    method, avatar, config, train, val_all = ctx.method, ctx.avatar, ctx.config, ctx.train, ctx.val
    state, log, start = ctx.state, ctx.log, ctx.start
    total = sum(s.iterations for s in stages)
    main = distributed.is_main()
    loss_file = (run / "losses.csv").open("a") if main else None
    while ctx.iteration < total:
        method.before_iteration(ctx)
        it = ctx.iteration
        stage = stage_at(stages, it)
        rows = torch.randperm(len(train), generator=gen)[: config.batch]
        loss, terms = backward_step(method, avatar, ctx.optimisers, train, rows, config, stage.name)
        factor = lr_factor(it, config)
        for name in stage.optimisers:
            for group in ctx.optimisers[name].param_groups:
                group["lr"] = group.setdefault("initial_lr", group["lr"]) * factor
            ctx.optimisers[name].step()
        ctx.iteration = it = it + 1
        if method.after_iteration(ctx):
            ctx.optimisers = method.optimisers(avatar, config)
        if main:
            loss_file.write(f"{it},{stage.name},{time.perf_counter() - start:.1f},{loss.item():.7g},"
                            + ",".join(f"{k}={v.item():.7g}" for k, v in terms.items()) + "\n")
        if progress:
            progress()
        if it % config.val_every == 0 or it == total:
            sub = torch.linspace(0, len(val_all) - 1, min(config.val_frames, len(val_all))).long()
            scores = validate(method, avatar, val_all.subset(sub), config, run / "val" if main else None)
            if main:
                with (run / "val.csv").open("a") as f:
                    f.write(f"{it},{time.perf_counter() - start:.1f},{scores['psnr']:.4f},{scores['ssim']:.4f}\n")
                log(f"iteration {it} ({stage.name}): loss {loss.item():.4f}, val PSNR {scores['psnr']:.2f} dB "
                    f"({len(sub)} frames, after {config.val_tto_steps} test-time fitting steps)")
        if it % config.checkpoint_every == 0 or it == total:
            if main:
                loss_file.flush()
            ctx.checkpoint()
    if main:
        loss_file.close()
        plot_progress(run)
    # After training: the method's hook, then the test-time fitting of the held-out frames, which
    # checkpoints every TTO_CHECKPOINT_FRAMES frames ("tested" in state.json).
    if "tested" not in state:
        state["train_seconds"] = time.perf_counter() - start
        state["after_training"] = method.after_training(ctx)
        state["tested"] = 0
        ctx.checkpoint()
    if state["tested"] < len(val_all):
        log(f"test-time optimisation of the validation frames {state['tested']}..{len(val_all)} "
            f"({config.tto_steps} + {config.tto_photometric_steps} photometric steps each)")
    remaining = torch.arange(state["tested"], len(val_all))
    for chunk in remaining.split(TTO_CHECKPOINT_FRAMES) if len(remaining) else ():  # (an empty range splits into one empty chunk)
        fit_frames(method, avatar, val_all, config, config.tto_steps, config.tto_photometric_steps, rows=chunk)
        state["tested"] = int(chunk[-1]) + 1
        ctx.checkpoint()
        log(f"test-time fitted {state['tested']}/{len(val_all)} validation frames")
    if not main:
        return {}  # rank 0 scores and writes; fit() hands its figures to every rank
    summary, per_frame = score(method, avatar, val_all, config, run / "val", max_images=8, landmarks=True)
    write_worst_frames(method, avatar, val_all, config, per_frame, run / "val_worst.png")
    metrics = {"method": method.name, "train_minutes": round(state["train_seconds"] / 60, 2),
               "device": str(torch.device(device))}
    metrics |= {f"val_{k}": v for k, v in summary.items()}
    metrics |= state["after_training"] | method.extra_scores(ctx)
    if (dataset / "gt" / "views").is_dir():
        from headforge.head.pose import from_tracking

        metrics |= score_novel_views(method, avatar, dataset, val_all, head, from_tracking(assets.tracking), config,
                                     picture=run / "novel_views.png")
    if (dataset / "gt" / "geometry.safetensors").is_file():
        export_geometry(avatar, dataset, run / "geometry.safetensors")
    metrics |= {"iterations": total, "resolution": config.resolution, "lpips": "n/a (no pretrained weights)",
                "dataset": dataset.name}
    (run / "metrics.tmp.json").write_text(json.dumps(metrics, indent=1))
    (run / "metrics.tmp.json").replace(run / "metrics.json")
    return metrics


@torch.no_grad()
def write_worst_frames(method: Method, avatar: Avatar, data: FrameData, config, per_frame: dict, path: Path) -> None:
    """A sheet of the held-out frames that agree worst with the avatar in expression (largest
    AKD; lowest head PSNR where no landmarks were found): rows of frame | avatar | |difference| x 4."""
    from headforge.metrics.protocol import composite
    from headforge.render.camera import Cameras
    from headforge.render.io import write_png

    key = per_frame.get("akd_px")
    if key is None or not np.isfinite(key).any():
        order = np.argsort(np.nan_to_num(per_frame["psnr_head"], nan=np.inf))
    else:
        order = np.argsort(-np.nan_to_num(key, nan=-np.inf))
    rows = torch.as_tensor(order[:WORST_FRAMES].copy())
    batch = data.batch(rows)
    r = method.render_for_scoring(avatar, avatar.frame_params(batch["index"]), Cameras.at_origin(data.K, len(rows), config.resolution))
    pred, gt = composite(r.rgb, batch["image"], batch["mask"], batch["region"])
    diff = ((pred - gt).abs() * 4).clamp(0, 1)
    write_png(path, torch.cat([torch.cat([gt[b], pred[b], diff[b]], 1) for b in range(len(rows))], 0).clamp(0, 1))


@torch.no_grad()
def novel_view_centres(dataset: Path, frames: torch.Tensor, head, tracked: dict) -> torch.Tensor:
    """(B, 3) camera-space orbit centres for the novel views of a synth subject's ``frames`` (B,),
    for an avatar built on the dataset's tracking.

    Synth orbits its camera about the head origin ``c`` (``gt/subject.json`` "translation").
    A monocular clip fixes a head only up to a scale about the camera (a head s times larger and
    s times farther gives the same images), and the tracked head sits s = z_tracked / z_gt as far
    as the subject's, measured at the eyeballs' midpoint (the tracked head model's ``eyeballs``
    posed at ``tracked``, the GT's ``eyes`` vertices in gt/geometry.safetensors). The avatar's
    counterpart of ``c`` is then s c, on the same camera ray: orbiting about ``c`` itself would
    charge the avatar its tracking's depth error (s (R (x - c) + c) = R (s x - s c) + s c)."""
    from safetensors.numpy import load_file

    from headforge.bench.synthetic import LABELS

    info = json.loads((dataset / "gt" / "subject.json").read_text())
    centre = torch.tensor(info["translation"], dtype=torch.float32)
    path = dataset / "gt" / "geometry.safetensors"
    if not path.is_file():
        raise HeadforgeError(f"{dataset} has novel views but no gt/geometry.safetensors to place their orbit: "
                             "a broken headforge synth subject (run headforge synth again)")
    gt = load_file(str(path))
    row = {int(f): i for i, f in enumerate(gt["frames"])}
    missing = [int(f) for f in frames.tolist() if int(f) not in row]
    if missing:
        raise HeadforgeError(f"{dataset}: novel views of frames {missing[:5]} have no ground-truth geometry")
    eyes = gt["labels"] == LABELS["eyes"]
    gt_z = torch.from_numpy(gt["vertices"][[row[int(f)] for f in frames.tolist()]][:, eyes, 2].mean(1))
    ids = head.model.region("eyeballs")
    tracked_z = head.vertices({k: v[frames.cpu()] for k, v in tracked.items()})[:, ids, 2].mean(1)
    return centre * (tracked_z / gt_z.float())[:, None]


def score_novel_views(method: Method, avatar: Avatar, dataset: Path, data: FrameData, head, tracked: dict,
                      config, picture: Path | None = None) -> dict:
    """The protocol's scores of the avatar from the novel views a synth subject carries
    (``gt/views/FRAME_yaw±D.png``, RGBA: the camera orbited by D degrees about the head's
    vertical axis through its origin), at the held-out frames' fitted parameters (NHA Sec. 4.4),
    the avatar's camera orbited by the same angle about its counterpart of that origin
    (:func:`novel_view_centres`); the scored regions from the tracked head model (``head``) at
    its ``tracked`` parameters. ``picture``: a PNG of the last scored frame, a row per angle of
    view | avatar | |difference| x 4, as scored (both on white inside the head region)."""
    from PIL import Image
    from scipy.spatial.transform import Rotation

    from headforge.head.pose import flip_matrix
    from headforge.metrics.protocol import composite, score_frames, summarise
    from headforge.render.camera import Cameras
    from headforge.render.io import write_png

    path = dataset / "gt" / "subject.json"
    if not path.is_file():
        return {}
    info = json.loads(path.read_text())
    out, tiles = {}, []
    flip = flip_matrix()
    position = {int(f): i for i, f in enumerate(data.index.tolist())}
    for yaw in info.get("novel_yaws", []):
        files = [p for p in sorted((dataset / "gt" / "views").glob(f"*_yaw{yaw:+.0f}.png")) if int(p.name[:5]) in position]
        rows = [position[int(p.name[:5])] for p in files]
        if not rows:
            continue
        R = torch.tensor(flip @ Rotation.from_euler("y", yaw, degrees=True).as_matrix() @ flip, dtype=torch.float32)
        centres = novel_view_centres(dataset, data.index[torch.tensor(rows).to(data.index.device)].cpu(), head, tracked)
        per_frame = {}
        for chunk in range(0, len(rows), config.batch):
            sel = torch.tensor(rows[chunk:chunk + config.batch])
            rgba = [np.asarray(Image.open(p).resize((config.resolution,) * 2, Image.BILINEAR), np.float32) / 255
                    for p in files[chunk:chunk + config.batch]]
            rgba = torch.from_numpy(np.stack(rgba)).to(data.K.device)
            B = len(sel)
            frames = data.index[sel.to(data.index.device)]
            c = centres[chunk:chunk + config.batch]
            t = (c - c @ R.T).to(data.K.device)  # c - R c, per frame
            cams = Cameras(data.K.expand(B, 3, 3), R.to(data.K.device).expand(B, 3, 3), t, config.resolution,
                           config.resolution)
            params = avatar.frame_params(frames)
            region, face = head.regions({k: v[frames.cpu()] for k, v in tracked.items()}, cams)  # tracked: on the CPU
            r = method.render_for_scoring(avatar, params, cams)
            s = score_frames(r.rgb, r.coverage, rgba[..., :3], rgba[..., 3], region, face, landmarks=False)
            for k, v in s.items():
                per_frame.setdefault(k, []).append(v)
        pred, gt = composite(r.rgb[-1:], rgba[-1:, ..., :3], rgba[-1:, ..., 3], region[-1:])
        tiles.append(torch.cat([gt[0], pred[0], ((pred[0] - gt[0]).abs() * 4).clamp(0, 1)], 1).cpu())
        summary = summarise({k: np.concatenate(v) for k, v in per_frame.items()})
        out |= {f"novel_yaw{yaw:+.0f}_{k}": v for k, v in summary.items() if k in ("psnr", "ssim", "l1", "psnr_head", "frames")}
    if picture is not None and tiles:
        write_png(picture, torch.cat(tiles, 0).clamp(0, 1))
    return out


@torch.no_grad()
def export_geometry(avatar: Avatar, dataset: Path, path: Path) -> None:
    """Camera-space surfaces of the avatar at the frames that carry ground truth in a synth
    dataset (the ``headforge eval`` geometry format): a mesh (``vertices``, ``faces``,
    ``face_vertices``, ``head_vertices``) or, for a point avatar, a point set (``points`` (T, N, 3)
    metres, unit ``normals`` (T, N, 3), world ``radius`` (T, N) metres; the same N in every frame;
    ``face_points`` / ``head_points`` (N,) bool when the avatar tells its regions; ``surfel_min_cos``
    (1,) when its points are drawn as surfels; ``hole_filling`` (1,) when its renders fill holes).
    Written to a temporary name and renamed."""
    from safetensors.numpy import load_file, save_file

    frames = load_file(str(dataset / "gt" / "geometry.safetensors"))["frames"]
    T = avatar.frames["translation"].shape[0]
    frames = frames[frames < T]
    parts = [avatar.geometry(avatar.frame_params(torch.from_numpy(chunk)))
             for chunk in np.array_split(frames, max(1, len(frames) // 8))]
    g = parts[0]
    as_np = lambda t: t.detach().cpu().numpy()  # noqa: E731
    cat = lambda key: np.concatenate([as_np(getattr(p, key)) for p in parts]).astype(np.float32)  # noqa: E731
    if g.faces is None:  # a point avatar: points with normals and splat radii
        if g.normals is None or g.radius is None:
            raise HeadforgeError("a point avatar's Geometry needs normals and radius for the geometry metrics")
        radius = np.concatenate([as_np(p.radius.expand(p.vertices.shape[:2])) for p in parts]).astype(np.float32)
        arrays = {"frames": frames.astype(np.int64), "points": cat("vertices"), "normals": cat("normals"),
                  "radius": radius}
        if g.face_vertices is not None and g.head_vertices is not None:  # the avatar's own regions per point
            arrays |= {"face_points": as_np(g.face_vertices), "head_points": as_np(g.head_vertices)}
        if g.surfel_min_cos > 0:
            arrays["surfel_min_cos"] = np.array([g.surfel_min_cos], np.float32)
        if g.hole_filling:
            arrays["hole_filling"] = np.array([1], np.uint8)
    else:
        arrays = {"frames": frames.astype(np.int64), "vertices": cat("vertices"),
                  "faces": as_np(g.faces).astype(np.int64), "face_vertices": as_np(g.face_vertices),
                  "head_vertices": as_np(g.head_vertices)}
    tmp = path.with_name(path.stem + ".tmp.safetensors")
    # safetensors' numpy writer copies the buffer as laid out: a strided array is written scrambled
    save_file({k: np.ascontiguousarray(v) for k, v in arrays.items()}, str(tmp))
    tmp.replace(path)


def _truncate_log(path: Path, iteration: int) -> None:
    """Keep the rows of a CSV log (first column: iteration) up to ``iteration``."""
    if path.is_file():
        rows = [line for line in path.read_text().splitlines() if line and int(line.split(",")[0]) <= iteration]
        path.write_text("".join(row + "\n" for row in rows))


def plot_progress(run: Path) -> None:
    """progress.png: training loss and validation PSNR against wall-clock minutes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [line.split(",") for line in (run / "losses.csv").read_text().splitlines() if line]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    if rows:
        t = np.array([float(r[2]) for r in rows]) / 60
        loss = np.array([float(r[3]) for r in rows])
        k = max(1, len(loss) // 100)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        axes[0].plot(t[len(t) - len(smooth):], smooth)
        axes[0].set(xlabel="minutes", ylabel="training loss", yscale="log")
    if (run / "val.csv").is_file():
        val = np.array([[float(v) for v in line.split(",")] for line in (run / "val.csv").read_text().splitlines() if line])
        if len(val):
            axes[1].plot(val[:, 1] / 60, val[:, 2], marker="o")
    axes[1].set(xlabel="minutes", ylabel="val. PSNR (dB, few frames, short fit)")
    fig.tight_layout()
    tmp = run / "progress.tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(run / "progress.png")


def evaluate_run(run: Path, dataset: Path, output: Path, log=print) -> dict:
    """The protocol's scores of a run's held-out frames (at its fitted parameters) against
    ``dataset``, the run's own dataset (checked by fingerprint), and of the novel views when it
    is a synth subject: ``output``/metrics.json, metrics.md, val_worst.png and frame | avatar PNGs."""
    from headforge.avatars.run import load_run
    from headforge.metrics.protocol import TrackedHead

    r = load_run(run)
    if RunAssets.from_dataset(dataset).fingerprint() != read_info(Path(run))["dataset"]["fingerprint"]:
        raise HeadforgeError(f"{dataset} is not the dataset {run} was trained on (its fingerprint differs)")
    head = TrackedHead(r.assets.head_data(), r.assets.tracking["shape"])
    val = FrameData(dataset, "val", r.config.resolution, head)
    log(f"scoring {len(val)} held-out frames of {run}")
    output.mkdir(parents=True, exist_ok=True)
    summary, per_frame = score(r.method, r.avatar, val, r.config, output, max_images=8, landmarks=True)
    write_worst_frames(r.method, r.avatar, val, r.config, per_frame, output / "val_worst.png")
    if (dataset / "gt" / "views").is_dir():
        from headforge.head.pose import from_tracking

        summary |= score_novel_views(r.method, r.avatar, dataset, val, head, from_tracking(r.assets.tracking), r.config,
                                     picture=output / "novel_views.png")
    (output / "metrics.json").write_text(json.dumps(summary, indent=1))
    table = ["| figure | value |", "| --- | --- |"] + [f"| {k} | {v} |" for k, v in summary.items()]
    (output / "metrics.md").write_text("\n".join(table) + "\n")
    return summary
