"""Driving from ARKit blendshapes: a Live Link Face–style CSV read into open-head's expressions and
poses, and ``render avatar --driving FILE.csv`` on a trained run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from headforge.errors import HeadforgeError


def test_a_live_link_face_csv_reads_into_expressions_and_rotations(tmp_path, open_head_data):
    from headforge.data.arkit import read_arkit_csv, write_arkit_csv

    names = list(open_head_data.expression_names)
    assert len(names) == 52
    rng = np.random.default_rng(0)
    weights = rng.uniform(0, 1, (130, 52))
    head = np.zeros((130, 3))
    head[:, 0] = np.linspace(-0.4, 0.4, 130)  # yaw only
    path = write_arkit_csv(tmp_path / "take.csv", names, weights, head, fps=60)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:3] == ["Timecode", "BlendShapeCount", "BrowDownLeft"] and header[-1] == "RightEyeRoll"
    clip = read_arkit_csv(path, names)  # the app's capitalised names match open-head's camelCase ones
    assert np.allclose(clip.weights, weights, atol=1e-6)
    assert clip.fps == 60  # 130 rows at 60 per second of timecode
    # yaw is a rotation about +y (head axes: the face turns toward +x, the subject's left)
    axis = clip.rotations["head"][-1] / np.linalg.norm(clip.rotations["head"][-1])
    assert np.allclose(axis, [0, 1, 0], atol=1e-6) and np.isclose(np.linalg.norm(clip.rotations["head"][-1]), 0.4)
    assert np.allclose(clip.rotations["eye_left"], 0)


def test_bad_csvs_are_one_line_errors(tmp_path, open_head_data):
    from headforge.data.arkit import read_arkit_csv

    names = list(open_head_data.expression_names)
    with pytest.raises(HeadforgeError, match="does not exist"):
        read_arkit_csv(tmp_path / "none.csv", names)
    (tmp_path / "short.csv").write_text("Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,1,0.5\n")
    with pytest.raises(HeadforgeError, match="lacks 51 of the head model's 52") as err:
        read_arkit_csv(tmp_path / "short.csv", names)
    assert "\n" not in str(err.value)
    (tmp_path / "text.csv").write_text(",".join(names) + "\n" + ",".join(["x"] * 52) + "\n")
    with pytest.raises(HeadforgeError, match="non-numeric"):
        read_arkit_csv(tmp_path / "text.csv", names)


def test_render_avatar_is_driven_by_a_csv(open_head_nha_run, tmp_path):
    """``render avatar RUN --driving take.csv``: one video frame per CSV row at the CSV's rate;
    the sequence opens the jaw where the CSV says jawOpen = 1 and turns the head by its yaw."""
    from typer.testing import CliRunner

    from headforge.avatars.reenact import arkit_sequence
    from headforge.avatars.run import load_run
    from headforge.cli import app
    from headforge.data.arkit import DEFAULT_FPS, write_arkit_csv
    from headforge.render.camera import Cameras

    r = load_run(open_head_nha_run)
    names = list(r.avatar.head.expression_names)
    weights = np.zeros((3, 52))
    weights[1, names.index("jawOpen")] = 1.0
    head = np.array([[0, 0, 0], [0, 0, 0], [0.5, 0, 0]])
    csv = write_arkit_csv(tmp_path / "take.csv", names, weights, head, fps=30)
    res = CliRunner().invoke(app, ["render", "avatar", str(open_head_nha_run), "-o", str(tmp_path / "csv.mp4"),
                                   "--driving", str(csv)])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout.strip().splitlines()[-1])["frames"] == 3
    assert (tmp_path / "csv.mp4").stat().st_size > 1000
    seq, fps = arkit_sequence(r.avatar, r.assets, csv)
    assert fps == DEFAULT_FPS  # three rows span no whole second of timecode
    K = r.assets.intrinsics(r.config.resolution)
    with torch.no_grad():
        out = [r.avatar.render({k: v[t:t + 1] for k, v in seq.items()}, Cameras.at_origin(K, 1, r.config.resolution))
               for t in range(3)]
    assert (out[1].rgb - out[0].rgb).abs().amax(-1).gt(0.05).sum() > 3  # the jaw opened
    assert (out[2].coverage - out[0].coverage).abs().gt(0.5).sum() > 20  # the head turned
    assert seq["translation"].std(0).max() == 0  # the avatar's mean framing
