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
