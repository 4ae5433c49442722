"""``headforge demo`` end to end at tiny settings: every step runs and the report is complete."""

from __future__ import annotations

import json
import shutil

from typer.testing import CliRunner


def test_the_demo_runs_end_to_end_and_its_run_folder_exports_and_renders(synth_bench, tmp_path):
    from headforge.avatars.nha.config import NHAConfig
    from headforge.cli import app
    from headforge.demo import run_demo

    out = tmp_path / "demo"
    # the synth step resumes from a finished benchmark folder: reuse the session's tiny one
    shutil.copytree(synth_bench[0], tmp_path / "demo.partial" / "synth")
    config = NHAConfig.quick()
    config.resolution = 96
    config.geometry_iters, config.texture_iters, config.joint_iters = 3, 2, 2
    config.val_every = config.checkpoint_every = 7
    config.val_frames, config.tto_steps, config.val_tto_steps, config.align_steps = 2, 1, 1, 1
    config.tex_grid, config.geo_width, config.tex_width = 32, 32, 32
    metrics = run_demo(out, config=config, device="cpu", log=lambda m: None, turntable=(3, 64, 2000))
    assert not (tmp_path / "demo.partial").exists()  # renamed only when complete
    for name in ("metrics.json", "metrics.md", "avatar_val.mp4", "avatar_orbit.mp4", "turntable.mp4", "turntable.png",
                 "fit_grace_hopper.png", "export/avatar.obj", "nha/progress.png", "nha/val_worst.png",
                 "eval_nha/metrics.json", "eval_tracked/metrics.json"):
        assert (out / name).is_file(), name
    assert json.loads((out / "metrics.json").read_text()) == metrics
    assert metrics["nha_iterations"] == 7 and 5 < metrics["nha_val_psnr"] < 60
    assert 0 < metrics["nha_normal_error_head_deg"] < 90 and 0 < metrics["tracked_hausdorff_full_mm"] < 50
    # the README's next steps work on the demo's run folder
    runner = CliRunner()
    res = runner.invoke(app, ["export", str(out / "nha"), "-o", str(tmp_path / "mesh"), "--format", "obj",
                              "--texture-size", "32"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["render", "avatar", str(out / "nha"), "-o", str(tmp_path / "orbit.mp4"), "--orbit",
                              "--max-frames", "2"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "orbit.mp4").stat().st_size > 1000
