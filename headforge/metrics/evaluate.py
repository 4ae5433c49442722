"""``headforge eval PRED GT``: image-quality metrics between two folders of images.

Files are matched by name (PNG/JPG). Optional ``masks`` folder (same names, foreground > 0.5)
gives masked metrics too. Every image of GT must have a prediction; sizes must agree. Writes
metrics.json (means and per-image values), metrics.md and grid.png (GT | prediction | error).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from headforge.errors import HeadforgeError
from headforge.paths import make_folder
from headforge.metrics import image as im

SUFFIXES = {".png", ".jpg", ".jpeg"}


def _read(path: Path, grey: bool = False) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as handle:
            return np.asarray(handle.convert("L" if grey else "RGB"), np.float32) / 255
    except (UnidentifiedImageError, OSError) as exc:
        raise HeadforgeError(f"cannot read image {path}: {exc}") from None


def _files(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        raise HeadforgeError(f"not a folder: {folder}")
    return {p.name: p for p in sorted(folder.iterdir()) if p.suffix.lower() in SUFFIXES}


def evaluate_folders(pred_dir: Path, gt_dir: Path, mask_dir: Path | None = None) -> dict:
    if mask_dir is not None and not mask_dir.is_dir():
        raise HeadforgeError(f"--masks folder not found: {mask_dir}")
    gt_files, pred_files = _files(gt_dir), _files(pred_dir)
    if not gt_files:
        raise HeadforgeError(f"no images in {gt_dir}")
    missing = sorted(set(gt_files) - set(pred_files))
    if missing:
        raise HeadforgeError(f"{len(missing)} ground-truth images have no prediction, e.g. {pred_dir / missing[0]}")
    per_image, rows = {}, []
    for name, gt_path in gt_files.items():
        gt = torch.from_numpy(_read(gt_path))[None]
        pred = torch.from_numpy(_read(pred_files[name]))[None]
        if pred.shape != gt.shape:
            raise HeadforgeError(f"{pred_files[name]} is {tuple(pred.shape[1:3])}, {gt_path} is {tuple(gt.shape[1:3])}")
        values = {"l1": im.l1(pred, gt).item(), "psnr": im.psnr(pred, gt).item(), "ssim": im.ssim(pred, gt).item()}
        if min(gt.shape[1:3]) > 160:
            values["ms_ssim"] = im.ms_ssim(pred, gt).item()
        values["cpbd"] = im.cpbd(pred[0])  # sharpness of the prediction (no reference needed)
        lp = im.lpips(pred, gt)
        values["lpips"] = None if lp is None else lp.item()
        if mask_dir is not None:
            mask_path = mask_dir / name
            if not mask_path.is_file():
                raise HeadforgeError(f"mask missing: {mask_path}")
            mask = torch.from_numpy(_read(mask_path, grey=True) > 0.5)[None]
            if mask.shape != gt.shape[:3]:
                raise HeadforgeError(f"{mask_path} does not match the size of {gt_path}")
            if not mask.any():
                raise HeadforgeError(f"{mask_path} is empty: no pixels to evaluate")
            values.update(l1_masked=im.l1(pred, gt, mask).item(), psnr_masked=im.psnr(pred, gt, mask).item(),
                          ssim_masked=im.ssim(pred, gt, mask).item())
        per_image[name] = values
        if len(rows) < 4:
            err = (pred - gt).abs().mean(-1, keepdim=True).expand_as(gt) * 4
            rows.append(torch.cat([gt[0], pred[0], err[0].clamp(0, 1)], 1).numpy())
    keys = list(next(iter(per_image.values())))
    mean = {}
    for k in keys:
        vals = [v[k] for v in per_image.values() if v.get(k) is not None]
        mean[k] = float(np.mean(vals)) if vals else "n/a"
    return {"images": len(per_image), "mean": mean, "per_image": per_image, "grid_rows": rows}


def write_report(result: dict, out_dir: Path) -> None:
    from headforge.render.io import write_png

    make_folder(out_dir)
    rows = result.pop("grid_rows")
    (out_dir / "metrics.json").write_text(json.dumps(result, indent=1))
    lines = [f"Evaluated {result['images']} images (every ground-truth image; none skipped).", "",
             "| metric | mean |", "| --- | --- |"]
    lines += [f"| {k} | {v if isinstance(v, str) else f'{v:.4f}'} |" for k, v in result["mean"].items()]
    (out_dir / "metrics.md").write_text("\n".join(lines) + "\n")
    if rows:
        width = max(r.shape[1] for r in rows)
        padded = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
        write_png(out_dir / "grid.png", np.concatenate(padded, 0))
