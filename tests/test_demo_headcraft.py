"""``headforge demo --method headcraft`` at tiny settings: every step runs, the report folder is
complete and renamed only when done; bad options are one-line errors."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

TINY = {"channel_base": 128, "channel_max": 16, "z_dim": 16, "w_dim": 16, "components": 4, "batch": 4}
REPORT = ("metrics.json", "metrics.md", "eval.json", "eval.md", "maps_train.png", "samples/sheet.png",
          "samples_truncated/sheet.png", "interpolation/strip.png", "animation.mp4", "scans_train/contact_sheet.png",
          "maps_held/summary.json", "run/run.json", "run/stylegan2/samples.png", "run/pca/checkpoint.safetensors")


def test_the_headcraft_demo_runs_end_to_end(tmp_path):
    from headforge.craft.demo import CraftDemoConfig, run_craft_demo

    out = tmp_path / "demo"
    cfg = CraftDemoConfig(train_identities=3, held_identities=2, map_size=32, register_steps_scale=0.02,
                          stylegan2_steps=2, resolution=32, settings=TINY, points=128, seeds=2, samples=2,
                          animation_frames=2, view_size=48, hair_voxel_mm=6.0, source="open-head")
    stale = tmp_path / "demo.partial"  # an interrupted demo of other sizes: not resumed, started afresh
    stale.mkdir()
    (stale / "settings.json").write_text(json.dumps({"train_identities": 99}))
    (stale / "stale.txt").write_text("left by another demo")
    metrics = run_craft_demo(out, cfg, log=lambda m: None)
    assert not (tmp_path / "demo.partial").exists()  # renamed only when complete
    assert not (out / "stale.txt").exists()
    for name in REPORT:
        assert (out / name).is_file(), name
    assert json.loads((out / "metrics.json").read_text()) == metrics
    assert metrics["train_maps"] == 4 and metrics["heldout_scans"] == 2 and metrics["stylegan2_steps"] == 2
    for m in ("stylegan2", "pca", "bare"):
        assert metrics[f"{m}_mmd"] > 0 and 0 <= metrics[f"{m}_cov"] <= 100
    assert metrics["memo_heldout_nn_mm"] > 0 and metrics["demo_minutes"] > 0


def test_headcraft_demo_bad_options_are_one_line_errors(tmp_path):
    from headforge.cli import app

    runner = CliRunner()
    for extra, words in ((["--video", str(tmp_path / "x.mp4")], "--video"), (["--iterations", "0"], "--iterations")):
        res = runner.invoke(app, ["demo", "--method", "headcraft", "-o", str(tmp_path / "d"), *extra])
        assert res.exit_code == 1 and words in res.output, res.output
        assert not (tmp_path / "d").exists() and not (tmp_path / "d.partial").exists()


@pytest.mark.slow
def test_the_headcraft_demo_at_its_default_size(tmp_path):
    """The command as a user runs it (about 15 min on the 2-core host: slow)."""
    from headforge.cli import app

    res = CliRunner().invoke(app, ["demo", "--method", "headcraft", "-o", str(tmp_path / "demo")])
    assert res.exit_code == 0, res.output
    metrics = json.loads((tmp_path / "demo" / "metrics.json").read_text())
    for name in REPORT:
        assert (tmp_path / "demo" / name).is_file(), name
    assert metrics["train_maps"] == 8 and metrics["stylegan2_steps"] == 300
