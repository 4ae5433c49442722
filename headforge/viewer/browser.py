"""Headless Chromium driving the viewer page (browser tests and the bake benchmark): the system's
``chromium`` (Debian's package) through Playwright, never a browser Playwright downloads. WebGL
runs on SwiftShader (the CPU), so no GPU is needed."""

from __future__ import annotations

import io
import os
import shutil
from contextlib import contextmanager

import numpy as np

from headforge.errors import HeadforgeError

CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox",
                 "--disable-dev-shm-usage"]


def chromium_path() -> str | None:
    """The Chromium executable: ``$HEADFORGE_CHROMIUM``, else ``chromium`` or ``chromium-browser``
    on the PATH; None when there is none."""
    given = os.environ.get("HEADFORGE_CHROMIUM")
    if given:
        return given if os.path.isfile(given) else None
    return shutil.which("chromium") or shutil.which("chromium-browser")


def missing() -> str | None:
    """Why a browser cannot be driven here (one line), or None when it can."""
    if chromium_path() is None:
        return "no chromium on the PATH (Debian: apt-get install -y chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the playwright package is not installed (pip install -e '.[dev]')"
    return None


@contextmanager
def page(width: int = 1000, height: int = 700):
    """A Playwright page in headless system Chromium; console errors are collected in
    ``page.errors`` (a list of strings)."""
    reason = missing()
    if reason:
        raise HeadforgeError(f"cannot drive a browser: {reason}")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
        try:
            pg = browser.new_page(viewport={"width": width, "height": height})
            pg.errors = []
            pg.on("pageerror", lambda e: pg.errors.append(str(e)))
            yield pg
        finally:
            browser.close()


def open_viewer(pg, url: str, size: int, play: bool = False, timeout_s: float = 120.0) -> None:
    """Load the viewer at ``url`` with a ``size`` x ``size`` canvas and wait for its model; a
    one-line error when the page reports one."""
    pg.goto(f"{url}?size={size}&play={int(play)}")
    pg.wait_for_function("window.viewer && (window.viewer.ready || window.viewer.error)", timeout=timeout_s * 1000)
    error = pg.evaluate("window.viewer.error")
    if error:
        raise HeadforgeError(f"the viewer page failed: {error}")


def canvas(pg) -> np.ndarray:
    """(H, W, 3) uint8: the viewer's canvas as shown."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(pg.locator("#view").screenshot())).convert("RGB"))


def frame(pg, index: int) -> np.ndarray:
    """The canvas showing frame ``index`` of the driving sequence from the clip's camera."""
    pg.evaluate(f"window.viewer.showFrame({int(index)})")
    return canvas(pg)
