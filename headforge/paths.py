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


def open_partial(output: Path, settings: dict, log) -> Path:
    """The work folder ``OUTPUT.partial`` of a resumable command: reused when it holds a run with
    the same ``settings`` (JSON-comparable), started afresh otherwise. The caller renames it to
    ``output`` when complete, so an interrupted run never looks finished."""
    import json
    import shutil

    work = output.with_name(output.name + ".partial")
    settings = json.loads(json.dumps(settings))
    if work.exists():
        previous = json.loads((work / "settings.json").read_text()) if (work / "settings.json").is_file() else None
        if previous != settings:
            log(f"{work} holds a run with other settings: starting over")
            shutil.rmtree(work)
        else:
            log(f"resuming the unfinished run in {work}")
    work.mkdir(parents=True, exist_ok=True)
    (work / "settings.json").write_text(json.dumps(settings))
    return work
