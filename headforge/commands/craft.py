"""``headforge craft``: HeadCraft -- scan sets, registration, UV displacement maps (part 1); the generative
model over the maps, sampling, interpolation, animation and evaluation (part 2)."""

from __future__ import annotations

from pathlib import Path

import typer

from headforge.errors import HeadforgeError

app = typer.Typer(help="HeadCraft: head scans -> registered template with free displacements -> UV displacement maps.",
                  no_args_is_help=True)


def _fail(exc: HeadforgeError) -> None:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(1)


@app.command("scans")
def scans(output: Path = typer.Option(..., "-o", "--output", help="folder to write the scan set into"),
          n: int = typer.Option(8, "--n", help="number of identities (each has a neutral scan; every 3rd an expression scan too)"),
          seed: int = typer.Option(0, "--seed", help="random seed"),
          harder: bool = typer.Option(True, help="cycle the harder variants (remeshed, noisy, holes, out-of-span)"),
          voxel_mm: float = typer.Option(3.0, help="hair volume voxel size (mm)"),
          workers: int = typer.Option(1, "--workers", help="local processes making scans (one thread each)")) -> None:
    """Generate head scans from anny identities with hair styles and exact ground truth."""
    from headforge.craft.scans import ScanSetConfig, generate_scans

    try:
        cfg = ScanSetConfig(n=n, seed=seed, harder=harder, hair_voxel_m=voxel_mm / 1000)
        keys = generate_scans(output, cfg, log=typer.echo, workers=workers)
    except HeadforgeError as exc:
        _fail(exc)
    typer.echo(f"{len(keys)} scans in {output} (contact sheet: {output / 'contact_sheet.png'})")


@app.command("register")
def register(scans: Path = typer.Argument(..., help="folder of scans: generated scan folders or OBJ/PLY/GLB/STL files"),
             output: Path = typer.Option(..., "-o", "--output", help="folder for the maps and registrations"),
             preset: str = typer.Option("quick", help="quick (CPU) or paper"),
             map_size: int = typer.Option(256, help="displacement map size in texels"),
             units: str = typer.Option("auto", help="external scans: auto, m, cm, mm or metres per unit"),
             up: str = typer.Option("+y", help="external scans: the file's up axis (+x, -x, +y, ...)"),
             forward: str = typer.Option("+z", help="external scans: the axis the face looks along"),
             only: str | None = typer.Option(None, help="comma-separated scan names to register"),
             ablation: str = typer.Option("both", help="both, stage1, stage2 or stage1_weights2 (Fig. 10)"),
             steps_scale: float = typer.Option(1.0, help="multiply every optimisation step count (smoke runs)"),
             ray: bool = typer.Option(False, "--ray", help="run the scans as tasks on a local Ray runtime"),
             ray_address: str | None = typer.Option(None, "--ray-address", help="Ray cluster address (implies --ray)"),
             workers: int = typer.Option(1, "--workers", help="local processes registering scans (one thread each; "
                                                               "for a many-core machine without Ray)"),
             model: str = typer.Option("open-head", "--model", "-m", help="open-head or flame"),
             flame_dir: str | None = typer.Option(None, "--flame-dir", help="folder with FLAME's generic_model.pkl")) -> None:
    """Register a folder of scans (resumable; one bad scan never stops the rest)."""
    from headforge.batch import run_batch, summary_table
    from headforge.craft.pipeline import list_scans, register_item

    try:
        if map_size < 32 or map_size > 4096 or map_size & (map_size - 1):
            raise HeadforgeError(f"--map-size must be a power of two within 32-4096, got {map_size}")
        items = list_scans(scans)
        if only:
            wanted = set(only.split(","))
            items = [it for it in items if it[0] in wanted]
            if not items:
                raise HeadforgeError(f"none of {sorted(wanted)} is in {scans}")
        opts = dict(preset=preset, map_size=map_size, units=units, up=up, forward=forward, head_model=model,
                    flame_dir=flame_dir, ablation=ablation, steps_scale=steps_scale)
        from headforge.craft.pipeline import ItemOptions, config_for

        config_for(ItemOptions(**opts))  # bad preset/ablation: fail before any work
        result = run_batch([(k, {"path": p, **opts}) for k, p in items], register_item, output,
                           ray=ray, ray_address=ray_address, workers=workers, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)
    typer.echo(summary_table(result, ["face_med_mm", "hair_med_mm", "s2r_med_mm", "edge_ratio", "lmk_mm", "roundtrip_mm"]))
    if not result.ok:
        typer.echo("error: no scan was registered", err=True)
        raise typer.Exit(1)
    typer.echo(f"{len(result.ok)} registered, {len(result.failed)} failed; maps in {output}")


# ---------------------------------------------------------------- part 2: the generative model
@app.command("train")
def train(maps: Path = typer.Argument(..., help="map folder: headforge craft register output (or <key>.png maps)"),
          output: Path = typer.Option(..., "-o", "--output", help="run folder (re-run the command to resume)"),
          model: str = typer.Option("stylegan2", "--model", help="stylegan2, pca, vae, vqvae or all"),
          preset: str = typer.Option("quick", help="quick (64 px, CPU) or paper (256 px, the paper's settings)"),
          holdout: float = typer.Option(0.2, help="fraction of identities held out of training"),
          steps: int | None = typer.Option(None, help="training steps (default: the preset's)"),
          seed: int = typer.Option(0, help="random seed (split and initialisation)"),
          settings: list[str] = typer.Option([], "--set", help="FIELD=VALUE config override, e.g. resolution=32"),
          device: str = typer.Option("cpu", help="cpu, cuda[:N] or auto (the paper preset wants a GPU)")) -> None:
    """Train HeadCraft's generative model (and baselines) over displacement maps. Under
    ``torchrun --nproc-per-node N`` the processes share each batch (gloo, on the CPU)."""
    from headforge import distributed
    from headforge.craft.generative import train as T
    from headforge.devices import resolve_device

    try:
        target = resolve_device(device)
        if distributed.launched() and target.type != "cpu":
            raise HeadforgeError("craft train under torchrun trains on the CPU (gloo): drop --device or run one process")
        methods = list(T.METHODS) if model == "all" else [model]
        for m in methods:
            T.config_class(m)
        opts = T.TrainOptions(preset=preset, holdout=holdout, seed=seed, steps=steps,
                              settings=T.parse_settings(settings, methods), device=str(target))
        distributed.init_from_environment("cpu")  # under torchrun: join the group (gloo); else nothing
        if distributed.active() and "vqvae" in methods:
            raise HeadforgeError("vqvae trains on one process only (its codebook's running averages are per process): "
                                 "run it without torchrun")
        if distributed.is_main():
            T.prepare_run(maps, output, methods, opts, log=typer.echo)
        distributed.barrier()  # run.json and the training maps exist before the ranks read them
        for m in methods:
            T.train_method(output, m, opts, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)
    finally:
        distributed.shutdown()


@app.command("sample")
def sample(run: Path = typer.Argument(..., help="run folder of headforge craft train"),
           n: int = typer.Option(8, "-n", help="number of samples"),
           output: Path | None = typer.Option(None, "-o", "--output", help="output folder (default RUN/samples_<model>)"),
           model: str = typer.Option("stylegan2", "--model", help="stylegan2, pca, vae, vqvae or bare"),
           truncation: float = typer.Option(1.0, help="truncation psi (0: the mean map; the paper shows 0.7)"),
           seed: int = typer.Option(0, help="sampling seed"),
           identity: Path | None = typer.Option(None, help="params.json whose 'shape' the maps are applied to "
                                                          "(default: sampled from the training identities)")) -> None:
    """Sample maps and meshes (map on a head-model identity) with a front/side/back sheet."""
    from headforge.craft.generative.sample import write_samples

    try:
        write_samples(run, model, output or run / f"samples_{model}", n, truncation, seed, identity, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)


@app.command("interpolate")
def interpolate(run: Path = typer.Argument(..., help="run folder of headforge craft train"),
                output: Path = typer.Option(..., "-o", "--output", help="output folder"),
                model: str = typer.Option("stylegan2", "--model", help="stylegan2, vae or pca"),
                seeds: tuple[int, int] = typer.Option((0, 1), help="the two latents' seeds"),
                steps: int = typer.Option(6, help="maps along the line, ends included"),
                truncation: float = typer.Option(1.0, help="truncation psi")) -> None:
    """Maps and meshes between two latents (a strip of front/side/back renders)."""
    from headforge.craft.generative.sample import interpolate as run_interpolate

    try:
        run_interpolate(run, model, output, steps, seeds, truncation, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)


@app.command("animate")
def animate(map_path: Path = typer.Argument(..., help="a map.png (of craft sample or craft register; its params.json "
                                                      "next to it gives the identity)"),
            driving: Path = typer.Option(..., "--driving", help="tracked dataset (headforge track) whose expressions drive it"),
            output: Path = typer.Option(..., "-o", "--output", help="output MP4"),
            max_frames: int = typer.Option(150, help="frames to render"),
            size: int = typer.Option(256, help="view size in pixels")) -> None:
    """Drive a displacement map with a tracked video's expressions and poses (TBN transfer, App. B.1)."""
    import json

    from headforge.craft import uvmap
    from headforge.craft.animate import animate as run_animate
    from headforge.craft.pipeline import template_for

    try:
        meta_path = map_path.parent / "params.json"
        meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
        head_model, levels = meta.get("head_model", "open-head"), meta.get("levels", 1)
        tpl, duv = template_for(head_model, levels)
        m = uvmap.read_map(map_path)
        m = uvmap.postprocess_seams(m, uvmap.texel_islands(duv, m.shape[0]) >= 0, duv, blend=0)
        run_animate(tpl, duv, m, meta.get("params"), driving, head_model, output, max_frames, size, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)


@app.command("eval")
def evaluate(run: Path = typer.Argument(..., help="run folder of headforge craft train"),
             heldout: Path = typer.Argument(..., help="map folder of held-out scans (headforge craft register output), or the training folder: "
                                                           "then the identities the run held out"),
             model: str = typer.Option("all", "--model", help="a trained model, bare, or all (every trained one + bare)"),
             points: int = typer.Option(2048, help="points per mesh (the paper: 10K)"),
             seeds: int = typer.Option(3, help="sampling seeds (mean and spread)"),
             truncation: float = typer.Option(1.0, help="truncation psi"),
             identities: str = typer.Option("sampled", help="sampled (the paper: random identity, expression, jaw) or "
                                                            "heldout (diagnostic: each map on a held-out scan's own "
                                                            "registered identity and expression)"),
             output: Path | None = typer.Option(None, "-o", "--output", help="JSON (+ .md table) to write (default RUN/eval.json)")) -> None:
    """MMD-CD, COV-CD, 1-NNA and JSD on held-out registrations, and the memorisation check."""
    from headforge.craft.generative import evaluate as E

    try:
        methods = None if model == "all" else [model]
        result = E.evaluate(run, heldout, methods, tuple(range(seeds)), points, truncation, log=typer.echo,
                            identities=identities)
        path = output or run / "eval.json"
        E.write(result, path)
    except HeadforgeError as exc:
        _fail(exc)
    typer.echo(E.table(result))
    typer.echo(f"written {path} and {path.with_suffix('.md')}")


@app.command("fit")
def fit(observation: Path = typer.Argument(..., help="a full scan (mesh file or generated scan folder), a depth map "
                                                     "(16-bit PNG or .npy + camera JSON) or a point cloud (PLY, PCD)"),
        model_run: Path = typer.Option(..., "--model", help="run folder of headforge craft train"),
        output: Path = typer.Option(..., "-o", "--output", help="output folder (completed mesh, map, latent, picture)"),
        method: str = typer.Option("stylegan2", "--method", help="stylegan2, pca, mean (the mean training map) or bare "
                                                                 "(the head model alone)"),
        preset: str = typer.Option("quick", help="quick (CPU) or paper"),
        camera: Path | None = typer.Option(None, help="depth maps: camera JSON with fx, fy, cx, cy (default: <depth>.json "
                                                     "or camera.json beside it)"),
        depth_scale: float | None = typer.Option(None, help="depth maps: metres per unit (PNG default 0.001, NPY 1)"),
        density: str = typer.Option("auto", help="auto, dense or sparse: the mask refinement threshold (0.83 / 2.5 mm)"),
        up: str | None = typer.Option(None, help="the file's up axis (default: -y for a cloud, a sensor's camera frame; "
                                                 "+y for a scan)"),
        forward: str | None = typer.Option(None, help="the axis the face looks along (default: -z cloud, +z scan)"),
        units: str | None = typer.Option(None, help="m, cm, mm or metres per unit (default: m cloud, guessed for a scan)"),
        noise: bool = typer.Option(True, help="the optional noise step of the StyleGAN2 fit"),
        seed: int = typer.Option(0, help="seed of the z initialisation"),
        z_starts: int = typer.Option(1, help="StyleGAN2 depth fits: z initialisations fitted side by side (the paper: 1)"),
        combine: str = typer.Option("best", help="with --z-starts > 1: best (the start that fits the observation best) or "
                                                 "mean (the mean of all completions: closer to the scan on average, less detail)"),
        truncation: float = typer.Option(1.0, help="StyleGAN2 depth fits: psi in (0, 1] pulling the z step's w toward the "
                                                   "average w (the paper fits with 1; its samples use 0.7)"),
        steps_scale: float = typer.Option(1.0, help="multiply every optimisation step count (smoke runs)"),
        gt: Path | None = typer.Option(None, "--gt", help="ground-truth scan folder (headforge craft scans) to score against")) -> None:
    """Fit a trained HeadCraft model to a full scan or to one depth map / point cloud (App. B.1)."""
    from headforge.craft.fit import FitOptions
    from headforge.craft.fit import fit as run_fit
    from headforge.craft.pipeline import torch_threads

    try:
        torch_threads()
        opts = FitOptions(method=method, preset=preset, camera=str(camera) if camera else None, depth_scale=depth_scale,
                          density=density, up=up, forward=forward, units=units, noise=noise, seed=seed,
                          z_starts=z_starts, combine=combine, truncation=truncation, steps_scale=steps_scale)
        run_fit(observation, model_run, output, opts, gt, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)


@app.command("transfer-hair")
def transfer_hair(face_fit: Path = typer.Argument(..., help="craft fit (or craft register) folder giving the face and identity"),
                  hair_fit: Path = typer.Argument(..., help="craft fit (or craft register) folder giving the hair (scalp island)"),
                  output: Path = typer.Option(..., "-o", "--output", help="output folder")) -> None:
    """A's face with B's hair: the scalp part of B's map on A's face part, seams blended (§4.3)."""
    from headforge.craft.fit import transfer_hair as run_transfer

    try:
        run_transfer(face_fit, hair_fit, output, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)


@app.command("depth")
def depth(scan: Path = typer.Argument(..., help="generated scan folder or mesh file (head axes, metres)"),
          output: Path = typer.Option(..., "-o", "--output", help="depth PNG to write (its camera JSON goes beside it)"),
          yaw: float = typer.Option(0.0, help="sensor yaw around the head, degrees (0: frontal)"),
          pitch: float = typer.Option(0.0, help="sensor pitch, degrees"),
          size: int = typer.Option(512, help="depth map size in pixels"),
          distance: float = typer.Option(0.6, help="sensor distance from the head, metres")) -> None:
    """Render a depth map of a scan as a consumer depth sensor would see it (16-bit PNG, 0.1 mm
    units, + camera JSON with the scan-to-camera pose): the observations of the depth benchmark."""
    import numpy as np

    from headforge.craft import observe as O
    from headforge.craft.pipeline import ItemOptions, load_any

    try:
        if not 32 <= size <= 4096:
            raise HeadforgeError(f"--size must be within 32-4096, got {size}")
        s, gt_ = load_any(scan, ItemOptions(units="m"))
        target = (np.nanmean(s.landmarks, 0) if s.landmarks is not None else s.vertices.mean(0)) + np.array([0, -0.02, -0.04])
        cam = O.depth_camera(target, yaw, pitch, size, distance)
        d = O.render_depth(s.vertices, s.faces, cam)
        if not (d > 0).any():
            raise HeadforgeError(f"the sensor sees nothing of {scan.name} from yaw {yaw}, pitch {pitch}")
        O.write_depth(output, d, cam)
    except HeadforgeError as exc:
        _fail(exc)
    typer.echo(f"depth map {output} ({int((d > 0).sum())} pixels) and camera {output.with_suffix('.json')}")
