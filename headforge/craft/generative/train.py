"""Training of HeadCraft's generative models over a map folder, in a self-contained run folder.

    RUN/
      run.json                   format, resolution, head model + subdivision level, the split
                                 by identity (train / held-out keys), the shape statistics of
                                 the training registrations, and per method its config and state
      train_maps.safetensors     the training maps (N, 3, R, R) in model units (memorisation check)
      <method>/checkpoint.safetensors   module weights (safetensors) + checkpoint.json
                                 (method, resolution, step, seconds); optimizer.pt (resume only)
      <method>/samples.png       a grid of samples at fixed latents, rewritten during training
      <method>/log.jsonl         losses

Methods: ``stylegan2``, ``vae``, ``vqvae``, ``pca`` (and the bare head model, which has
nothing to train). Everything is written to a temp name and renamed; a killed run resumes from
its last checkpoint when the same command is run again.

On a GPU (``--device cuda``) the modules and the training maps live on the device; every random
draw (batches, latents, noise) still comes from the CPU's seeded generators, so a run draws the same
numbers on either device and a checkpoint written on one resumes on the other.

Over processes (``torchrun``, :mod:`headforge.distributed`, gloo: training runs on the CPU):
every rank draws the same global batches (the same seeded generators), trains on its share
with the gradients averaged before each optimiser step (StyleGAN2, the VAE); PCA is fitted
identically on every rank; the VQ-VAE trains on one process only. Rank 0 alone writes.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from headforge import distributed
from headforge.craft.generative import data as D
from headforge.errors import HeadforgeError

FORMAT = "headforge-craft-run"
VERSION = 1
METHODS = ("stylegan2", "pca", "vae", "vqvae")


def config_class(method: str):
    from headforge.craft.generative.pca import PCAConfig
    from headforge.craft.generative.stylegan2 import StyleGAN2Config
    from headforge.craft.generative.vae import VAEConfig
    from headforge.craft.generative.vqvae import VQVAEConfig

    classes = {"stylegan2": StyleGAN2Config, "pca": PCAConfig, "vae": VAEConfig, "vqvae": VQVAEConfig}
    if method not in classes:
        raise HeadforgeError(f"unknown model {method!r}; choose {', '.join(METHODS)} or all")
    return classes[method]


def make_config(method: str, preset: str, settings: dict | None = None):
    """The preset's config with ``settings`` (field -> value) applied where the method has the
    field (``--set resolution=32`` reaches every method; ``--set channel_base=512`` StyleGAN2)."""
    if preset not in ("quick", "paper"):
        raise HeadforgeError(f"unknown preset {preset!r}; choose quick or paper")
    cfg = getattr(config_class(method), preset)()
    for key, value in (settings or {}).items():
        if hasattr(cfg, key):
            old = getattr(cfg, key)
            try:
                if isinstance(old, list):
                    new = [type(old[0])(x) for x in str(value).split(",")]
                elif isinstance(old, bool):
                    new = str(value).lower() in ("1", "true", "yes")
                elif old is None:
                    new = float(value)
                else:
                    new = type(old)(value)
            except ValueError:
                raise HeadforgeError(f"--set {key}={value}: not a valid {type(old).__name__}") from None
            setattr(cfg, key, new)
    return cfg


def parse_settings(pairs: list[str], methods: list[str]) -> dict:
    """``["key=value", ...]`` -> dict; a one-line error for a key no model has (a key another
    model has is ignored by the chosen ones, so one ``--set`` list serves every model)."""
    out = {}
    for pair in pairs:
        if "=" not in pair:
            raise HeadforgeError(f"--set expects FIELD=VALUE, got {pair!r}")
        k, v = pair.split("=", 1)
        if not any(hasattr(config_class(m).quick(), k) for m in METHODS):
            raise HeadforgeError(f"no model has a setting {k!r}")
        out[k] = v
    return out


def build(method: str, cfg, face: np.ndarray | None = None, seed: int = 0):
    """The trainer object of a method (its modules, optimizers and ``train_step``)."""
    if method == "stylegan2":
        from headforge.craft.generative.stylegan2 import StyleGAN2Trainer

        return StyleGAN2Trainer(cfg, face, seed)
    if method == "vae":
        from headforge.craft.generative.vae import VAETrainer

        return VAETrainer(cfg, seed)
    if method == "vqvae":
        from headforge.craft.generative.vqvae import VQVAETrainer

        return VQVAETrainer(cfg, seed)
    if method == "pca":
        return PCATrainer(cfg)
    raise HeadforgeError(f"unknown model {method!r}")


class PCATrainer:
    def __init__(self, cfg):
        from headforge.craft.generative.pca import PCAModel

        self.cfg = cfg
        self.model = PCAModel(cfg)
        self.step = 0

    def modules(self):
        return {"model": self.model}

    def optimizers(self):
        return {}

    def fit(self, maps: torch.Tensor) -> None:
        self.model.fit(maps)
        self.step = 1


# ---------------------------------------------------------------- run folder
def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".partial")
    write(tmp)
    tmp.replace(path)


def write_json(path: Path, data: dict) -> None:
    _atomic_write(path, lambda p: p.write_text(json.dumps(data, indent=1, default=float)))


def read_run(run: str | Path) -> dict:
    run = Path(run)
    path = run / "run.json"
    if not path.is_file():
        raise HeadforgeError(f"{run} is not a headcraft run folder (run.json missing): train one with headforge craft train")
    meta = json.loads(path.read_text())
    if meta.get("format") != FORMAT:
        raise HeadforgeError(f"{run} is not a headcraft run folder (format {meta.get('format')!r})")
    if meta.get("version") != VERSION:
        raise HeadforgeError(f"{run} was written by run version {meta.get('version')}, this headforge reads {VERSION}")
    return meta


def trainer_device(trainer) -> torch.device:
    """The device a trainer's modules live on (its first module's first tensor)."""
    for module in trainer.modules().values():
        for t in module.state_dict().values():
            return t.device
    return torch.device("cpu")


def move(trainer, device: torch.device | str) -> None:
    """Put a trainer's modules and extra state on ``device``; its optimizers follow (their
    state is created lazily, or cast to the parameters' device when a checkpoint is loaded)."""
    for module in trainer.modules().values():
        module.to(device)
    if hasattr(trainer, "extra_state"):
        trainer.load_extra_state({k: v.to(device) for k, v in trainer.extra_state().items()})


def save_checkpoint(folder: Path, method: str, trainer, resolution: int, seconds: float, done: bool) -> None:
    from safetensors.torch import save_file

    folder.mkdir(parents=True, exist_ok=True)
    tensors = {}
    for name, module in trainer.modules().items():
        for k, v in module.state_dict().items():
            tensors[f"{name}.{k}"] = v.detach().cpu().contiguous().clone()
    if hasattr(trainer, "extra_state"):
        tensors.update({f"extra.{k}": v.detach().cpu().contiguous() for k, v in trainer.extra_state().items()})
    _atomic_write(folder / "checkpoint.safetensors", lambda p: save_file(tensors, str(p)))
    opts = {k: o.state_dict() for k, o in trainer.optimizers().items()}
    if opts:
        _atomic_write(folder / "optimizer.pt", lambda p: torch.save({"optimizers": opts, "rng": torch.get_rng_state()}, str(p)))
    write_json(folder / "checkpoint.json", {"method": method, "resolution": resolution, "step": trainer.step,
                                           "seconds": seconds, "done": done,
                                           "images": getattr(trainer, "images", None)})


def load_checkpoint(folder: Path, method: str, trainer, resolution: int, optimizers: bool = True) -> dict:
    """Fill ``trainer`` from ``folder``; one-line errors for another method or resolution."""
    from safetensors.torch import load_file

    meta_path = folder / "checkpoint.json"
    if not meta_path.is_file():
        raise HeadforgeError(f"no {method} checkpoint in {folder.parent}: train it with headforge craft train --model {method}")
    meta = json.loads(meta_path.read_text())
    if meta.get("method") != method:
        raise HeadforgeError(f"{folder / 'checkpoint.safetensors'} is a {meta.get('method')} checkpoint, not {method}")
    if meta.get("resolution") != resolution:
        raise HeadforgeError(f"{folder / 'checkpoint.safetensors'} was trained at {meta.get('resolution')} px, "
                             f"this run is {resolution} px")
    tensors = load_file(str(folder / "checkpoint.safetensors"))
    for name, module in trainer.modules().items():
        state = {k[len(name) + 1:]: v for k, v in tensors.items() if k.startswith(name + ".")}
        try:
            module.load_state_dict(state)
        except RuntimeError as exc:
            first = str(exc).strip().splitlines()[0]
            raise HeadforgeError(f"{folder / 'checkpoint.safetensors'} does not fit this {method} config ({first[:120]})") from None
    if hasattr(trainer, "load_extra_state"):
        trainer.load_extra_state({k[6:]: v for k, v in tensors.items() if k.startswith("extra.")})
    trainer.step = int(meta["step"])
    if meta.get("images") is not None:
        trainer.images = int(meta["images"])
    if optimizers and (folder / "optimizer.pt").is_file():
        state = torch.load(str(folder / "optimizer.pt"), weights_only=False, map_location="cpu")  # any device's
        for k, opt in trainer.optimizers().items():
            opt.load_state_dict(state["optimizers"][k])
        torch.set_rng_state(state["rng"])
    return meta


# ---------------------------------------------------------------- prepare and train
@dataclass
class TrainOptions:
    preset: str = "quick"
    holdout: float = 0.2
    seed: int = 0
    steps: int | None = None  # overrides the preset's step count (and the prior's epochs scale with it)
    head_model: str | None = None
    settings: dict | None = None  # config fields (--set FIELD=VALUE)
    threads: int = 1  # torch threads while training (set after every import: some reset it)
    device: str = "cpu"  # the device the modules train on (resolved by the caller)


def prepare_run(maps_folder: str | Path, run: str | Path, methods: list[str], options: TrainOptions, log=print) -> dict:
    """Read the maps, split by identity, write run.json and train_maps (or check an existing
    run folder agrees: same resolution, same split)."""
    run = Path(run)
    resolutions = {make_config(m, options.preset, options.settings).resolution for m in methods}
    if len(resolutions) != 1:
        raise HeadforgeError(f"the {options.preset} presets of {methods} disagree on the resolution: {sorted(resolutions)}")
    R = resolutions.pop()
    existing = read_run(run) if (run / "run.json").is_file() else None
    if existing is not None and existing["resolution"] != R:
        raise HeadforgeError(f"{run} holds a run at {existing['resolution']} px; the {options.preset} preset trains at {R} px "
                             "(use another -o)")
    ms = D.load_maps(maps_folder, R, options.head_model)
    train_idx, held_idx = D.split_by_identity(ms.items, options.holdout, options.seed)
    if len(train_idx) < 2:
        raise HeadforgeError(f"{maps_folder} has {len(train_idx)} training maps after the split; need at least 2")
    if existing is not None:
        if existing["train_keys"] != [ms.items[i].key for i in train_idx]:
            raise HeadforgeError(f"{run} was trained on another map set or split (use another -o)")
        return existing
    run.mkdir(parents=True, exist_ok=True)
    from safetensors.torch import save_file

    maps = D.to_model(ms.maps[train_idx])
    _atomic_write(run / "train_maps.safetensors", lambda p: save_file({"maps": maps}, str(p)))
    meta = {"format": FORMAT, "version": VERSION, "resolution": R, "head_model": ms.head_model, "levels": ms.levels,
            "scale_m": D.SCALE_M, "maps": str(Path(maps_folder).resolve()), "preset": options.preset,
            "seed": options.seed, "holdout": options.holdout,
            "train_keys": [ms.items[i].key for i in train_idx], "heldout_keys": [ms.items[i].key for i in held_idx],
            "face_replaced": ms.face_replaced, "shape_stats": D.shape_stats([ms.items[i] for i in train_idx]),
            "methods": {}}
    write_json(run / "run.json", meta)
    log(f"{len(train_idx)} training maps ({len({ms.items[i].identity for i in train_idx})} identities), "
        f"{len(held_idx)} held out; {len(ms.face_replaced)} faces replaced by the neutral scan's; {R} px")
    return meta


def train_maps(run: str | Path) -> torch.Tensor:
    from safetensors.torch import load_file

    return load_file(str(Path(run) / "train_maps.safetensors"))["maps"]


def sample_grid(maps: torch.Tensor, columns: int = 8) -> np.ndarray:
    """(B, 3, R, R) model units -> uint8 grid of map previews (+-2 cm -> 0..1)."""
    from headforge.craft import uvmap

    tiles = [uvmap.map_preview(m) for m in D.from_model(maps)]
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + columns], 1) for i in range(0, len(tiles), columns)]
    return np.concatenate(rows, 0)


def _write_png(path: Path, img: np.ndarray) -> None:
    import cv2

    def w(p):
        if not cv2.imwrite(str(p) + ".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
            raise HeadforgeError(f"cannot write {path}")
        Path(str(p) + ".png").replace(p)

    _atomic_write(path, w)


def train_method(run: str | Path, method: str, options: TrainOptions, log=print) -> dict:
    """Train (or resume) one method in a prepared run folder; returns its record in run.json."""
    run = Path(run)
    meta = read_run(run)
    main = distributed.is_main()
    if method == "vqvae" and distributed.active():
        raise HeadforgeError("vqvae trains on one process only (its codebook's running averages are per process): "
                             "run it without torchrun")
    cfg = make_config(method, options.preset, options.settings)
    if options.steps is not None:
        if options.steps < 1:
            raise HeadforgeError(f"--steps must be positive, got {options.steps}")
        if method == "vqvae":
            cfg.prior_epochs = max(1, round(cfg.prior_epochs * options.steps / cfg.steps))
        cfg.steps = options.steps
    if cfg.resolution != meta["resolution"]:
        raise HeadforgeError(f"{run} is a {meta['resolution']} px run; {method} {options.preset} trains at {cfg.resolution} px")
    folder = run / method
    face = D.face_texels(meta["head_model"], meta["levels"], cfg.resolution)
    trainer = build(method, cfg, face, options.seed)
    move(trainer, options.device)  # before any checkpoint is loaded: Adam casts its state to the parameters' device
    maps = train_maps(run).to(options.device)
    # one thread: on the shared 2-core host two threads ran a StyleGAN2 step 10x slower
    # (13-20 s against 1.3 s), and importing the registration stack had reset the count to 2
    torch.set_num_threads(max(1, options.threads))
    seconds = 0.0
    if (folder / "checkpoint.json").is_file():
        ck = load_checkpoint(folder, method, trainer, cfg.resolution)  # extra state lands on the modules' device
        seconds = float(ck.get("seconds", 0.0))
        if ck.get("done") and trainer.step >= cfg.steps:
            if main:
                log(f"{method}: already trained ({trainer.step} steps)")
            return meta["methods"].get(method, {})
        if main:
            log(f"{method}: resuming at step {trainer.step}")
    distributed.barrier()  # every rank has read the checkpoint before rank 0 writes the next
    if main:
        folder.mkdir(parents=True, exist_ok=True)
    fixed_z = torch.Generator().manual_seed(1234)
    t0 = time.time()
    logs = {}
    if method == "pca":
        trainer.fit(maps)
    else:
        import contextlib
        import io

        from rich.progress import Progress

        rng = torch.Generator().manual_seed(options.seed * 7919 + trainer.step)  # the same batches on every rank
        with (Progress(transient=True, disable=not main) as progress,
              open(folder / "log.jsonl", "a") if main else contextlib.nullcontext(io.StringIO()) as logf):
            task = progress.add_task(f"{method}", total=cfg.steps, completed=trainer.step)
            while trainer.step < cfg.steps:
                idx = torch.randint(len(maps), (cfg.batch,), generator=rng)
                logs = trainer.train_step(maps[idx])
                progress.update(task, completed=trainer.step,
                                description=f"{method} " + " ".join(f"{k} {v:.3g}" for k, v in logs.items()))
                if trainer.step % 25 == 0:
                    logf.write(json.dumps({"step": trainer.step, **logs}) + "\n")
                last = trainer.step >= cfg.steps
                if not main:  # pictures and checkpoints: rank 0 (the ranks hold the same weights)
                    continue
                if trainer.step % cfg.sample_every == 0 or last:
                    if method == "vqvae" and not last:
                        with torch.no_grad():
                            trainer.model.eval()
                            grid = trainer.model(maps[:16])[0].cpu()  # reconstructions until the prior exists
                    elif method != "vqvae":
                        grid = sample_latents(method, trainer, 16, 1.0, fixed_z.manual_seed(1234))
                    else:
                        grid = None
                    if grid is not None:
                        _write_png(folder / "samples.png", sample_grid(grid))
                if trainer.step % cfg.checkpoint_every == 0 and not last:
                    save_checkpoint(folder, method, trainer, cfg.resolution, seconds + time.time() - t0, False)
        if method == "vqvae":
            log(f"vqvae: PixelCNN prior, {cfg.prior_epochs} epochs over the training codes")
            logs.update(trainer.fit_prior(maps))
    seconds += time.time() - t0
    record = {"config": asdict(cfg), "preset": options.preset, "steps": trainer.step,
              "train_minutes": seconds / 60, "last_losses": logs}
    if main:
        if method in ("pca", "vqvae"):
            _write_png(folder / "samples.png", sample_grid(sample_latents(method, trainer, 16, 1.0, fixed_z.manual_seed(1234))))
        save_checkpoint(folder, method, trainer, cfg.resolution, seconds, True)
        meta = read_run(run)
        meta["methods"][method] = record
        write_json(run / "run.json", meta)
        log(f"{method}: {trainer.step} steps in {seconds / 60:.1f} min; samples in {folder / 'samples.png'}")
    distributed.barrier()  # run.json holds this method before any rank starts the next
    return record


# ---------------------------------------------------------------- sampling
def latent_dim(method: str, trainer) -> int | None:
    if method == "stylegan2":
        return trainer.cfg.z_dim
    if method in ("vae", "pca"):
        return trainer.model.latent_dim()
    return None


def sample_latents(method: str, trainer, n: int, truncation: float, generator: torch.Generator,
                   z: torch.Tensor | None = None) -> torch.Tensor:
    """(n, 3, R, R) model-unit maps from standard-normal latents drawn with ``generator`` (or
    the given ``z``). Truncation: StyleGAN2 lerps w toward w_avg; VAE and PCA scale z;
    VQ-VAE uses it as the PixelCNN temperature. Truncation 0 is the mean map (StyleGAN2:
    the map of w_avg; PCA: the training mean; VAE: the decoding of z = 0), for VQ-VAE the greedy
    decoding."""
    with torch.no_grad():
        if method == "vqvae":
            return trainer.sample(n, truncation, generator).cpu()
        if z is None:
            z = torch.randn(n, latent_dim(method, trainer), generator=generator)
        z = z.to(trainer_device(trainer))
        out = []
        for k in range(0, len(z), 16):
            if method == "stylegan2":
                out.append(trainer.sample(z[k:k + 16], truncation))
            else:
                trainer.model.eval()
                out.append(trainer.model.sample(z[k:k + 16], truncation))
        return torch.cat(out).cpu()


def load_trained(run: str | Path, method: str):
    """(trainer with the final weights, run meta) for sampling; one-line errors for a method
    that was not trained here or a checkpoint of another method/resolution."""
    run = Path(run)
    meta = read_run(run)
    if method not in METHODS:
        raise HeadforgeError(f"unknown model {method!r}; choose {', '.join(METHODS)}")
    rec = meta["methods"].get(method)
    if rec is None:
        trained = ", ".join(meta["methods"]) or "none"
        raise HeadforgeError(f"{run} has no trained {method} (trained: {trained})")
    cfg = config_class(method)(**rec["config"])
    face = D.face_texels(meta["head_model"], meta["levels"], cfg.resolution)
    trainer = build(method, cfg, face)
    load_checkpoint(run / method, method, trainer, meta["resolution"], optimizers=False)
    return trainer, meta
