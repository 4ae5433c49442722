"""``headforge batch track|fit``: per-item isolation, resume, summary.json/md, Ray, bad input.

Tracking a real clip takes minutes, so the CLI tests put a tiny stand-in in place of the
per-video job (:func:`fake_track`: it reads the file and fails on a corrupt one, as the tracker
does); ``batch fit`` runs the real engine on tiny rendered datasets. The real measurement over
the shared clips is in docs/batch_and_distributed.md.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

import headforge.commands.batch as batch_cmd
from headforge.cli import app

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parent / "data"))


def fake_track(key: str, payload: dict, workdir: Path) -> dict:
    """A stand-in for one tracking job: a "video" is a text file holding a frame count."""
    from headforge.errors import HeadforgeError

    text = Path(payload["video"]).read_text()
    if not text.strip().isdigit():
        raise HeadforgeError(f"cannot decode {payload['video']}")
    (workdir / "dataset.json").write_text(json.dumps({"frames": int(text), "max_frames": payload["options"]["max_frames"]}))
    return {"frames_valid": int(text)}


def _videos(folder: Path, corrupt: bool = True) -> Path:
    folder.mkdir()
    (folder / "a.mp4").write_text("12")
    (folder / "b.mov").write_text("7")
    if corrupt:
        (folder / "broken.mp4").write_text("not a video")
    (folder / "notes.txt").write_text("ignored")
    return folder


def _invoke(*args):
    res = CliRunner().invoke(app, [str(a) for a in args])
    return res.exit_code, res.output + ("" if res.exception is None else str(res.exception))


def test_batch_track_isolates_failures_resumes_and_writes_a_summary(tmp_path, monkeypatch):
    monkeypatch.setattr(batch_cmd, "track_item", fake_track)
    videos, out = _videos(tmp_path / "videos"), tmp_path / "out"
    code, output = _invoke("batch", "track", videos, "-o", out, "--max-frames", 5)
    assert code == 0, output
    assert json.loads((out / "a" / "dataset.json").read_text()) == {"frames": 12, "max_frames": 5}
    assert (out / "b" / "result.json").is_file() and not (out / "broken").exists()
    assert not list(out.glob(".*.partial"))
    summary = json.loads((out / "summary.json").read_text())
    status = {r["key"]: r["status"] for r in summary["items"]}
    assert status == {"a": "ok", "b": "ok", "broken": "failed"}
    assert summary["ok"] == 2 and summary["failed"] == 1 and summary["backend"] == "in-process"
    errors = {r["key"]: r["error"] for r in summary["items"]}
    assert errors["broken"].startswith("cannot decode") and "broken.mp4" in errors["broken"]
    assert json.loads((out / "_failed" / "broken.json").read_text())["error"] == errors["broken"]
    md = (out / "summary.md").read_text()
    assert md.startswith("| item | status | s | frames_valid |") and "| broken | failed |" in md
    assert "2 ok, 1 failed, 0 skipped" in md

    # a re-run skips the finished items and retries the failed one (fixed now)
    (videos / "broken.mp4").write_text("3")
    before = (out / "a" / "result.json").stat().st_mtime_ns
    code, output = _invoke("batch", "track", videos, "-o", out)
    assert code == 0, output
    summary = json.loads((out / "summary.json").read_text())
    assert {r["key"]: r["status"] for r in summary["items"]} == {"a": "skipped", "b": "skipped", "broken": "ok"}
    assert summary["skipped"] == 2 and (out / "a" / "result.json").stat().st_mtime_ns == before
    assert not (out / "_failed" / "broken.json").exists()
    assert "1 ok, 0 failed, 2 skipped" in (out / "summary.md").read_text()


def test_batch_bad_input_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr(batch_cmd, "track_item", fake_track)
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no videos here")
    cases = [(["batch", "track", tmp_path / "empty", "-o", tmp_path / "o1"], "no videos in"),
             (["batch", "track", tmp_path / "missing", "-o", tmp_path / "o1"], "is not a folder"),
             (["batch", "fit", "nha", tmp_path / "empty", "-o", tmp_path / "o2"], "no datasets in"),
             (["batch", "fit", "no-such-method", tmp_path / "empty", "-o", tmp_path / "o2"], "unknown avatar method"),
             (["batch", "track", _videos(tmp_path / "v"), "-o", tmp_path / "o3", "--cpus-per-item", 0], "--cpus-per-item"),
             # a port nothing listens on: refused at once, before Ray is started
             (["batch", "track", tmp_path / "v", "-o", tmp_path / "o4", "--ray-address", "127.0.0.1:9"], "does not answer")]
    for args, message in cases:
        res = CliRunner().invoke(app, [str(a) for a in args])
        assert res.exit_code != 0, (args, res.output)
        error = res.exception
        assert message in str(error), (args, str(error))
        assert "\n" not in str(error)
    # every video broken: the batch itself fails (non-zero exit), the summary still written
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "x.mp4").write_text("garbage")
    res = CliRunner().invoke(app, ["batch", "track", str(tmp_path / "bad"), "-o", str(tmp_path / "o5")])
    assert res.exit_code != 0 and "no item of the batch succeeded" in str(res.exception)
    assert json.loads((tmp_path / "o5" / "summary.json").read_text())["failed"] == 1


def test_an_unanswering_ray_address_fails_within_the_timeout():
    """A routable address that never answers: the probe gives up after its timeout."""
    import time

    from headforge.batch.runner import check_reachable
    from headforge.errors import HeadforgeError

    start = time.perf_counter()
    with pytest.raises(HeadforgeError, match="does not answer"):
        check_reachable("127.0.0.1:9", timeout=0.5)  # refused
    check_reachable("auto")  # no port: left to Ray
    assert time.perf_counter() - start < 5


def test_batch_fit_trains_each_dataset_and_resumes(tmp_path, monkeypatch, tiny_head, interrupt_after):
    """The real engine per dataset (tiny NHA runs): a dataset with broken tracking fails alone,
    a run a killed batch left half done continues from its checkpoint."""
    from conftest import write_rendered_dataset
    from make_nha_reference import reference_settings

    from headforge.avatars import registry
    from headforge.avatars.engine import fit
    from headforge.commands.fit import make_config

    tiny = reference_settings() | {"geometry_iters": 2, "texture_iters": 2, "joint_iters": 2, "tto_steps": 2,
                                   "val_every": 6, "checkpoint_every": 3}
    settings = [a for k, v in tiny.items() for a in ("--set", f"{k}={v}")]
    datasets = tmp_path / "datasets"
    write_rendered_dataset(datasets / "s1", tiny_head, frames=5, val=2)
    write_rendered_dataset(datasets / "s2", tiny_head, frames=5, val=2, seed=1)
    write_rendered_dataset(datasets / "s3", tiny_head, frames=5, val=2, seed=2)
    (datasets / "s2" / "tracking.safetensors").write_bytes(b"broken")
    out = tmp_path / "runs"
    # s3: a batch killed in s3's fifth iteration (its last checkpoint at 3)
    config = make_config(registry.get("nha"), "quick", None, None, [a for a in settings if a != "--set"])
    with pytest.raises(KeyboardInterrupt):
        fit("nha", datasets / "s3", out / ".s3.partial", config, log=lambda m: None, progress=interrupt_after(5))
    code, output = _invoke("batch", "fit", "nha", datasets, "-o", out, "--device", "cpu", *settings)
    assert code == 0, output
    summary = json.loads((out / "summary.json").read_text())
    assert [r["status"] for r in summary["items"]] == ["ok", "failed", "ok"]
    assert (out / "s1" / "metrics.json").is_file() and (out / "s1" / "run.json").is_file()
    assert summary["items"][0]["metrics"]["val_psnr"] > 0
    assert "iteration 6" in (out / "_logs" / "s1.log").read_text()
    assert "resuming" in (out / "_logs" / "s3.log").read_text()
    assert [line.split(",")[0] for line in (out / "s3" / "losses.csv").read_text().splitlines()] == list("123456")
    code, output = _invoke("batch", "fit", "nha", datasets, "-o", out, "--device", "cpu", *settings)
    assert [r["status"] for r in json.loads((out / "summary.json").read_text())["items"]] == ["skipped", "failed", "skipped"]


def test_batch_track_on_a_local_ray_runtime(tmp_path, monkeypatch):
    """The Ray path end to end through the CLI (one local runtime start, a few seconds)."""
    pytest.importorskip("ray")
    monkeypatch.setattr(batch_cmd, "track_item", fake_track)  # Ray workers import it from this module
    videos, out = _videos(tmp_path / "videos"), tmp_path / "out"
    code, output = _invoke("batch", "track", videos, "-o", out, "--ray", "--ray-cpus", 2, "--cpus-per-item", 1)
    assert code == 0, output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["backend"] == "ray"
    assert {r["key"]: r["status"] for r in summary["items"]} == {"a": "ok", "b": "ok", "broken": "failed"}
    assert json.loads((out / "b" / "dataset.json").read_text())["frames"] == 7
    assert "cannot decode" in {r["key"]: r["error"] for r in summary["items"]}["broken"]
    # more GPUs per item than the runtime has: refused, not queued forever
    code, output = _invoke("batch", "track", videos, "-o", out, "--ray", "--ray-cpus", 1, "--gpus-per-item", 1)
    assert code != 0 and "asks for 1 GPU(s)" in output, output


def test_a_batch_item_caps_numba_threads_as_well_as_torch(monkeypatch):
    """A Ray worker starts before its item: the item's CPUs must cap numba's parallel kernels too
    (``devices.limit_threads``), or two 1-CPU items on 2 cores each run them on both cores."""
    import numba
    import torch

    torch_before, numba_before = torch.get_num_threads(), numba.get_num_threads()
    try:
        batch_cmd._threads(1)
        assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
        batch_cmd._threads(64)  # never more than numba was started with
        assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    finally:
        torch.set_num_threads(torch_before)
        numba.set_num_threads(numba_before)
