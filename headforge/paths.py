"""Where headforge keeps derived data (the built open-head model, caches)."""

from __future__ import annotations

import os
from pathlib import Path

import platformdirs


def cache_dir() -> Path:
    """``$HEADFORGE_CACHE`` if set, else the user cache directory (e.g. ~/.cache/headforge)."""
    root = os.environ.get("HEADFORGE_CACHE")
    path = Path(root) if root else Path(platformdirs.user_cache_dir("headforge"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def make_folder(path: Path) -> Path:
    """``mkdir -p``, with a one-line error when a file is in the way or it is not allowed."""
    from headforge.errors import HeadforgeError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise HeadforgeError(f"cannot write to {path}: a file of that name exists (expected a folder)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HeadforgeError(f"cannot create folder {path}: {exc.strerror or exc}") from None
    return path


def open_partial(output: Path, settings: dict, log) -> Path:
    """The work folder ``OUTPUT.partial`` of a resumable command: reused when it holds a run with
    the same ``settings`` (JSON-comparable), started afresh otherwise. The caller renames it to
    ``output`` when complete, so an interrupted run never looks finished."""
    import json
    import shutil

    from headforge.errors import HeadforgeError

    work = output.with_name(output.name + ".partial")
    if output.exists() and not output.is_dir():
        raise HeadforgeError(f"cannot write to {output}: a file of that name exists (expected a folder)")
    settings = json.loads(json.dumps(settings))
    if work.exists():
        try:
            previous = json.loads((work / "settings.json").read_text())
        except (OSError, ValueError):  # absent, or half-written when the run was killed
            previous = None
        if previous != settings:
            log(f"{work} holds a run with other settings: starting over")
            shutil.rmtree(work)
        else:
            log(f"resuming the unfinished run in {work}")
    make_folder(work)
    (work / "settings.json").write_text(json.dumps(settings))
    return work


def publish_report(work: Path, output: Path, metrics: dict) -> None:
    """Finish a report folder: ``metrics.json`` and a ``metrics.md`` table (figure | value) written
    into the work folder (``OUTPUT.partial``), which then replaces ``output``."""
    import json
    import shutil

    (work / "metrics.json").write_text(json.dumps(metrics, indent=2))
    table = ["| figure | value |", "| --- | --- |"] + [f"| {k} | {v} |" for k, v in metrics.items()]
    (work / "metrics.md").write_text("\n".join(table) + "\n")
    if output.exists():
        shutil.rmtree(output)
    work.replace(output)
