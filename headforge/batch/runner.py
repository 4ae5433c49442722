"""A resumable batch runner with per-item isolation, in-process or on Ray.

Layout of an output folder (``output``)::

    output/<key>/            one finished item (whatever ``fn`` wrote) + result.json
    output/.<key>.partial/   an item being written (never looks complete; removed on failure)
    output/_failed/<key>.json  the one-line error (and traceback) of a failed item
    output/summary.json      every item's status, seconds, metrics (rewritten at the end)

An item is done when ``output/<key>/result.json`` exists: a rerun skips it (resume) and
retries failed ones. ``fn(key, payload, workdir) -> dict`` writes its files into ``workdir``
(the partial folder) and returns the item's metrics; the runner renames the folder when it
returns. One item's exception never stops the others. With ``ray=True`` each item is a Ray
task (a local runtime, or the cluster at ``ray_address``); ``fn`` must then be picklable
(a module-level function).
"""

from __future__ import annotations

import json
import shutil
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from headforge.errors import HeadforgeError

RESULT = "result.json"
FAILED = "_failed"


@dataclass
class ItemResult:
    key: str
    status: str  # "ok", "failed", "skipped" (done by an earlier run)
    seconds: float = 0.0
    metrics: dict = field(default_factory=dict)
    error: str = ""


@dataclass
class BatchResult:
    items: list[ItemResult]

    @property
    def ok(self) -> list[ItemResult]:
        return [r for r in self.items if r.status in ("ok", "skipped")]

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.items if r.status == "failed"]


def _atomic_json(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(data, indent=2, default=float))
    tmp.replace(path)


def _check_key(key: str) -> None:
    if not key or key.startswith((".", "_")) or "/" in key or "\\" in key:
        raise HeadforgeError(f"invalid batch item name {key!r} (no leading '.' or '_', no slashes)")


def run_item(fn: Callable[[str, Any, Path], dict], key: str, payload: Any, output: str | Path) -> ItemResult:
    """Run one item in isolation: every exception becomes a failed :class:`ItemResult`."""
    output = Path(output)
    final, work = output / key, output / f".{key}.partial"
    failed = output / FAILED / f"{key}.json"
    start = time.perf_counter()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    try:
        metrics = fn(key, payload, work) or {}
        seconds = time.perf_counter() - start
        _atomic_json(work / RESULT, {"key": key, "status": "ok", "seconds": seconds, "metrics": metrics})
        if final.exists():
            shutil.rmtree(final)
        work.rename(final)
        failed.unlink(missing_ok=True)
        return ItemResult(key, "ok", seconds, metrics)
    except Exception as exc:  # noqa: BLE001 -- isolation is the point
        seconds = time.perf_counter() - start
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if not isinstance(exc, HeadforgeError):
            message = f"{type(exc).__name__}: {message}"
        shutil.rmtree(work, ignore_errors=True)
        failed.parent.mkdir(parents=True, exist_ok=True)
        _atomic_json(failed, {"key": key, "error": message, "traceback": traceback.format_exc()})
        return ItemResult(key, "failed", seconds, error=message)


def _done(output: Path, key: str) -> ItemResult | None:
    path = output / key / RESULT
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return ItemResult(key, "skipped", float(data.get("seconds", 0.0)), data.get("metrics", {}))


def _ray_results(fn, todo, output: Path, ray_address: str | None, num_cpus: int | None, log) -> list[ItemResult]:
    try:
        import ray
    except ImportError:
        raise HeadforgeError("--ray needs the ray package: pip install 'headforge[ray]'") from None
    started = False
    if not ray.is_initialized():
        kwargs = dict(include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
        if ray_address:
            ray.init(address=ray_address, **kwargs)
        else:
            # a local runtime's workers import what this process can (fn may live in a script/test)
            import os
            import sys

            path = os.pathsep.join(p for p in sys.path if p)
            ray.init(num_cpus=num_cpus, runtime_env={"env_vars": {"PYTHONPATH": path}}, **kwargs)
        started = True
    try:
        remote = ray.remote(max_retries=0)(run_item)
        refs = {key: remote.remote(fn, key, payload, str(output)) for key, payload in todo}
        results = []
        for key, ref in refs.items():
            try:
                results.append(ray.get(ref))
            except Exception as exc:  # noqa: BLE001 -- a dead worker fails its item only
                lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip() and not set(ln.strip()) <= set("^~")]
                message = lines[-1] if lines else type(exc).__name__  # Ray puts the cause last
                results.append(ItemResult(key, "failed", error=f"ray: {message}"))
                shutil.rmtree(output / f".{key}.partial", ignore_errors=True)
            log(f"{key}: {results[-1].status}")
        return results
    finally:
        if started:
            ray.shutdown()


def run_batch(items: Sequence[tuple[str, Any]], fn: Callable[[str, Any, Path], dict], output: str | Path, *,
              ray: bool = False, ray_address: str | None = None, num_cpus: int | None = None,
              resume: bool = True, log: Callable[[str], None] = print) -> BatchResult:
    """Run ``fn`` over ``items`` ((key, payload) pairs) into ``output``; see the module doc."""
    output = Path(output)
    keys = [k for k, _ in items]
    for key in keys:
        _check_key(key)
    if len(set(keys)) != len(keys):
        raise HeadforgeError("batch item names must be unique")
    output.mkdir(parents=True, exist_ok=True)
    results: dict[str, ItemResult] = {}
    todo = []
    for key, payload in items:
        done = _done(output, key) if resume else None
        if done is not None:
            results[key] = done
        else:
            todo.append((key, payload))
    if todo:
        if ray or ray_address:
            for r in _ray_results(fn, todo, output, ray_address, num_cpus, log):
                results[r.key] = r
        else:
            for i, (key, payload) in enumerate(todo):
                r = run_item(fn, key, payload, output)
                results[key] = r
                log(f"[{i + 1}/{len(todo)}] {key}: {r.status}" + (f" ({r.error})" if r.error else f" in {r.seconds:.1f} s"))
    ordered = BatchResult([results[k] for k in keys])
    _atomic_json(output / "summary.json", {"items": [asdict(r) for r in ordered.items],
                                           "ok": len(ordered.ok), "failed": len(ordered.failed)})
    return ordered


def summary_table(result: BatchResult, columns: Sequence[str] = ()) -> str:
    """A plain-text table: key, status, seconds, the chosen metric columns, error."""
    head = ["item", "status", "s", *columns, "error"]
    rows = []
    for r in result.items:
        vals = []
        for c in columns:
            v = r.metrics.get(c, "")
            vals.append(f"{v:.3g}" if isinstance(v, (int, float)) else str(v))
        rows.append([r.key, r.status, f"{r.seconds:.1f}", *vals, r.error])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    line = lambda cells: "  ".join(str(c).ljust(w) for c, w in zip(cells, widths)).rstrip()
    return "\n".join([line(head), line(["-" * w for w in widths]), *map(line, rows)])
