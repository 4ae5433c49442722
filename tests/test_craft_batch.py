"""headforge.batch: per-item isolation, resume, atomic item folders, optional Ray."""

import json

import pytest

from headforge.batch import run_batch, summary_table
from headforge.errors import HeadforgeError

CALLS = []


def _square(key, payload, workdir):
    CALLS.append(key)
    if payload < 0:
        raise HeadforgeError(f"negative input {payload}")
    if payload == 13:
        raise ZeroDivisionError("unlucky")
    (workdir / "out.txt").write_text(str(payload * payload))
    return {"value": payload * payload}


def test_continues_past_broken_items_and_resumes(tmp_path):
    CALLS.clear()
    items = [("a", 2), ("bad", -1), ("b", 3), ("crash", 13)]
    result = run_batch(items, _square, tmp_path, log=lambda m: None)
    assert [r.status for r in result.items] == ["ok", "failed", "ok", "failed"]
    assert result.items[1].error == "negative input -1"
    assert result.items[3].error == "ZeroDivisionError: unlucky"
    assert (tmp_path / "b" / "out.txt").read_text() == "9"
    assert not (tmp_path / "bad").exists() and not list(tmp_path.glob(".*.partial"))
    assert json.loads((tmp_path / "_failed" / "bad.json").read_text())["error"] == "negative input -1"
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["ok"] == 2 and summary["failed"] == 2

    # resume: done items are skipped, failed ones retried (and succeed once fixed)
    CALLS.clear()
    again = run_batch([("a", 2), ("bad", 4), ("b", 3), ("crash", 13)], _square, tmp_path, log=lambda m: None)
    assert CALLS == ["bad", "crash"]
    assert [r.status for r in again.items] == ["skipped", "ok", "skipped", "failed"]
    assert again.items[0].metrics == {"value": 4}
    assert not (tmp_path / "_failed" / "bad.json").exists()
    table = summary_table(again, ["value"])
    assert "crash" in table and "ZeroDivisionError" in table and "16" in table


def test_bad_item_names(tmp_path):
    with pytest.raises(HeadforgeError, match="unique"):
        run_batch([("a", 1), ("a", 2)], _square, tmp_path)
    with pytest.raises(HeadforgeError, match="invalid batch item name"):
        run_batch([("../x", 1)], _square, tmp_path)


@pytest.mark.slow
def test_ray_backend(tmp_path):
    pytest.importorskip("ray")
    result = run_batch([("a", 2), ("bad", -1), ("b", 5)], _square, tmp_path, ray=True, num_cpus=1,
                       log=lambda m: None)
    assert [r.status for r in result.items] == ["ok", "failed", "ok"]
    assert (tmp_path / "b" / "out.txt").read_text() == "25"
    assert result.items[1].error == "negative input -1"


def test_worker_processes_isolate_items_like_one_process(tmp_path):
    items = [("a", 2), ("bad", -1), ("b", 3), ("crash", 13)]
    lines = []
    result = run_batch(items, _square, tmp_path, workers=2, log=lines.append)
    assert [r.status for r in result.items] == ["ok", "failed", "ok", "failed"]  # in the items' order
    assert result.items[1].error == "negative input -1" and result.items[3].error == "ZeroDivisionError: unlucky"
    assert (tmp_path / "b" / "out.txt").read_text() == "9" and len(lines) == 4
    assert not list(tmp_path.glob(".*.partial"))
    assert json.loads((tmp_path / "summary.json").read_text())["backend"] == "2 processes"
    again = run_batch(items, _square, tmp_path, workers=2, log=lambda m: None)
    assert [r.status for r in again.items] == ["skipped", "failed", "skipped", "failed"]
    with pytest.raises(HeadforgeError, match="workers"):
        run_batch(items, _square, tmp_path, workers=0)
    with pytest.raises(HeadforgeError, match="not both"):
        run_batch(items, _square, tmp_path, workers=2, ray=True)
