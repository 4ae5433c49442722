"""A resumable batch runner with per-item isolation, in-process or on Ray.

Layout of an output folder (``output``)::

    output/<key>/            one finished item (whatever ``fn`` wrote) + result.json
    output/.<key>.partial/   an item being written (never looks complete; removed on failure)
    output/_failed/<key>.json  the one-line error (and traceback) of a failed item
    output/summary.json      every item's status, seconds, metrics; the batch's wall time
    output/summary.md        the same as a Markdown table (rewritten at the end)

An item is done when ``output/<key>/result.json`` exists: a rerun skips it (resume) and
retries failed ones. ``fn(key, payload, workdir) -> dict`` writes its files into ``workdir``
(the partial folder) and returns the item's metrics; the runner renames the folder when it
returns. One item's exception never stops the others. With ``keep_partial`` a partial folder
left by a killed run is handed to ``fn`` again (for items that resume their own work, e.g.
training); it is still removed when ``fn`` raises. With ``ray=True`` each item is a Ray task
(a local runtime, or the cluster at ``ray_address``) asking for ``cpus_per_item`` CPUs and
``gpus_per_item`` GPUs; with ``workers=N`` (N > 1) the items run in N local processes (for a
many-core machine without Ray). Both need ``fn`` picklable (a module-level function).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import sys
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
    wall_seconds: float = 0.0  # this run, start to end
    item_seconds: float = 0.0  # the items this run ran (not the skipped ones), one after another

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


def run_item(fn: Callable[[str, Any, Path], dict], key: str, payload: Any, output: str | Path,
             keep_partial: bool = False) -> ItemResult:
    """Run one item in isolation: every exception becomes a failed :class:`ItemResult`."""
    output = Path(output)
    final, work = output / key, output / f".{key}.partial"
    failed = output / FAILED / f"{key}.json"
    start = time.perf_counter()
    if not keep_partial:
        shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
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


CONNECT_TIMEOUT_S = 10.0  # how long a --ray-address may take to accept a connection
GCS_WAIT_ENV = "RAY_gcs_server_port_wait_time_s"  # Ray's connect attempts (about 2 s each; 20 by default)


def check_reachable(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """Fail fast (HeadforgeError) when ``address`` (``host:port`` or ``ray://host:port``) does
    not accept a TCP connection within ``timeout`` seconds: ``ray.init`` retries an address
    that does not answer for a long time. ``auto``/``local`` (no port) are left to Ray."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        return
    try:
        with socket.create_connection((host or "127.0.0.1", int(port)), timeout=timeout):
            pass
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or type(exc).__name__)
        raise HeadforgeError(f"the Ray cluster at {address} does not answer ({reason} within {timeout:g} s)") from None


def _ray_init(ray, ray_address: str | None, num_cpus: int | None, timeout: float) -> None:
    kwargs = dict(include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    try:
        if ray_address:
            # the port may answer without being Ray (a proxy): bound Ray's own attempts too
            bounded = {GCS_WAIT_ENV: str(max(1, round(timeout / 2)))}
            previous = {k: os.environ.get(k) for k in bounded}
            os.environ.update(bounded)
            try:
                ray.init(address=ray_address, **kwargs)
            finally:
                for k, v in previous.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
        else:
            # a local runtime's workers import what this process can (fn may live in a script/test)
            path = os.pathsep.join(p for p in sys.path if p)
            ray.init(num_cpus=num_cpus, runtime_env={"env_vars": {"PYTHONPATH": path}}, **kwargs)
    except Exception as exc:  # noqa: BLE001 -- Ray's own errors are many-line
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        where = f"the Ray cluster at {ray_address}" if ray_address else "a local Ray runtime"
        raise HeadforgeError(f"cannot start {where}: {lines[0] if lines else type(exc).__name__}") from None


def _check_resources(ray, cpus: float, gpus: float) -> None:
    """A task asking more than the cluster has would wait forever: refuse it up front."""
    total = ray.cluster_resources()
    for name, want in (("CPU", cpus), ("GPU", gpus)):
        if want > total.get(name, 0.0):
            raise HeadforgeError(f"each item asks for {want:g} {name}(s), the Ray cluster has {total.get(name, 0.0):g}")


def _ray_results(fn, todo, output: Path, ray_address: str | None, num_cpus: int | None, log, cpus: float,
                 gpus: float, keep_partial: bool, timeout: float) -> list[ItemResult]:
    if ray_address:  # an address that does not answer is the user's error with or without ray
        check_reachable(ray_address, timeout)
    try:
        import ray
    except ImportError:
        raise HeadforgeError("--ray needs the ray package: pip install 'headforge[ray]'") from None
    started = False
    if not ray.is_initialized():
        _ray_init(ray, ray_address, num_cpus, timeout)
        started = True
    try:
        _check_resources(ray, cpus, gpus)
        remote = ray.remote(max_retries=0)(run_item).options(num_cpus=cpus, num_gpus=gpus)
        refs = {remote.remote(fn, key, payload, str(output), keep_partial): key for key, payload in todo}
        results, pending = [], list(refs)
        while pending:  # in the order they finish
            ready, pending = ray.wait(pending, num_returns=1)
            key = refs[ready[0]]
            try:
                results.append(ray.get(ready[0]))
            except Exception as exc:  # noqa: BLE001 -- a dead worker fails its item only
                lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip() and not set(ln.strip()) <= set("^~")]
                message = lines[-1] if lines else type(exc).__name__  # Ray puts the cause last
                results.append(ItemResult(key, "failed", error=f"ray: {message}"))
                if not keep_partial:  # a killed item that resumes its own work continues from it next time
                    shutil.rmtree(output / f".{key}.partial", ignore_errors=True)
            r = results[-1]
            log(f"[{len(results)}/{len(refs)}] {key}: {r.status}" + (f" ({r.error})" if r.error else f" in {r.seconds:.1f} s"))
        return results
    finally:
        if started:
            ray.shutdown()


def cap_threads(threads: int) -> None:
    """Process-pool initializer: cap the numeric libraries' threads before they are imported, so that N
    workers on N cores do not each start a thread per core."""
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[name] = str(threads)


def _process_results(fn, todo, output: Path, workers: int, cpus: float, keep_partial: bool, log) -> list[ItemResult]:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    # spawn, not fork: a forked child of a process that already ran torch/OpenMP threads can deadlock
    context = multiprocessing.get_context("spawn")
    results = []
    with ProcessPoolExecutor(workers, mp_context=context, initializer=cap_threads,
                             initargs=(max(1, int(cpus)),)) as pool:
        futures = {pool.submit(run_item, fn, key, payload, str(output), keep_partial): key for key, payload in todo}
        for future in as_completed(futures):
            key = futures[future]
            try:
                results.append(future.result())
            except BrokenProcessPool as exc:  # a worker died (killed, out of memory): its items fail, not the batch
                results.append(ItemResult(key, "failed", error=f"worker process died: {exc}"))
                if not keep_partial:
                    shutil.rmtree(output / f".{key}.partial", ignore_errors=True)
            r = results[-1]
            log(f"[{len(results)}/{len(futures)}] {key}: {r.status}" + (f" ({r.error})" if r.error else f" in {r.seconds:.1f} s"))
    return results


def run_batch(items: Sequence[tuple[str, Any]], fn: Callable[[str, Any, Path], dict], output: str | Path, *,
              ray: bool = False, ray_address: str | None = None, num_cpus: int | None = None, workers: int = 1,
              cpus_per_item: float = 1.0, gpus_per_item: float = 0.0, keep_partial: bool = False,
              columns: Sequence[str] = (), resume: bool = True, connect_timeout: float = CONNECT_TIMEOUT_S,
              log: Callable[[str], None] = print) -> BatchResult:
    """Run ``fn`` over ``items`` ((key, payload) pairs) into ``output``; see the module doc.
    ``num_cpus``: the CPUs of a local Ray runtime (default: the machine's); ``columns``: the
    metrics shown in summary.md; ``workers``: local processes (1: in this process)."""
    if cpus_per_item < 0 or gpus_per_item < 0:
        raise HeadforgeError("CPUs and GPUs per item must be >= 0")
    if workers < 1:
        raise HeadforgeError(f"workers must be >= 1, got {workers}")
    if workers > 1 and (ray or ray_address):
        raise HeadforgeError("choose Ray or local worker processes, not both")
    start = time.perf_counter()
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
            for r in _ray_results(fn, todo, output, ray_address, num_cpus, log, cpus_per_item, gpus_per_item,
                                  keep_partial, connect_timeout):
                results[r.key] = r
        elif workers > 1 and len(todo) > 1:
            for r in _process_results(fn, todo, output, min(workers, len(todo)), cpus_per_item, keep_partial, log):
                results[r.key] = r
        else:
            for i, (key, payload) in enumerate(todo):
                r = run_item(fn, key, payload, output, keep_partial)
                results[key] = r
                log(f"[{i + 1}/{len(todo)}] {key}: {r.status}" + (f" ({r.error})" if r.error else f" in {r.seconds:.1f} s"))
    ordered = BatchResult([results[k] for k in keys])
    ran = [r for r in ordered.items if r.status != "skipped"]
    ordered.wall_seconds = time.perf_counter() - start
    ordered.item_seconds = sum(r.seconds for r in ran)
    _atomic_json(output / "summary.json", {"items": [asdict(r) for r in ordered.items],
                                           "ok": len(ordered.ok), "failed": len(ordered.failed),
                                           "skipped": len(ordered.items) - len(ran),
                                           "backend": "ray" if (ray or ray_address) else
                                           f"{workers} processes" if workers > 1 else "in-process",
                                           "wall_seconds": ordered.wall_seconds,
                                           "item_seconds": ordered.item_seconds})
    tmp = output / "summary.md.partial"
    tmp.write_text(markdown_table(ordered, columns))
    tmp.replace(output / "summary.md")
    return ordered


def _rows(result: BatchResult, columns: Sequence[str]) -> tuple[list[str], list[list[str]]]:
    head = ["item", "status", "s", *columns, "error"]
    rows = []
    for r in result.items:
        vals = []
        for c in columns:
            v = r.metrics.get(c, "")
            vals.append(f"{v:.3g}" if isinstance(v, (int, float)) else str(v))
        rows.append([r.key, r.status, f"{r.seconds:.1f}", *vals, r.error])
    return head, rows


def summary_table(result: BatchResult, columns: Sequence[str] = ()) -> str:
    """A plain-text table: key, status, seconds, the chosen metric columns, error."""
    head, rows = _rows(result, columns)
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    line = lambda cells: "  ".join(str(c).ljust(w) for c, w in zip(cells, widths)).rstrip()
    return "\n".join([line(head), line(["-" * w for w in widths]), *map(line, rows)])


def markdown_table(result: BatchResult, columns: Sequence[str] = ()) -> str:
    """summary.md: the items as a Markdown table (key, status, seconds, ``columns``, error),
    then the counts and the wall time against the items' own seconds added up."""
    head, rows = _rows(result, columns)
    cell = lambda v: str(v).replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    skipped = sum(r.status == "skipped" for r in result.items)
    lines += ["", f"{len(result.ok) - skipped} ok, {len(result.failed)} failed, {skipped} skipped (done by an earlier run); "
              f"wall time {result.wall_seconds:.1f} s, the items run here took {result.item_seconds:.1f} s added up."]
    return "\n".join(lines) + "\n"
