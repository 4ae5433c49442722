"""PNG/MP4 writers and the turntable command."""

from __future__ import annotations

import json

import av
import numpy as np
import pytest
from typer.testing import CliRunner

from headforge.cli import app
from headforge.errors import HeadforgeError
from headforge.render.io import write_mp4, write_png


def test_mp4_round_trip_and_odd_sizes(tmp_path):
    frames = [np.full((33, 47, 3), i / 10) for i in range(5)]
    path = write_mp4(tmp_path / "v.mp4", frames, fps=10, total=5)
    with av.open(str(path)) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(decoded) == 5 and decoded[0].shape == (34, 48, 3)
    assert abs(decoded[3].mean() / 255 - 0.3) < 0.03
    assert not list(tmp_path.glob("*.partial*"))


def test_interrupted_video_leaves_nothing_that_looks_finished(tmp_path):
    def frames():
        yield np.zeros((16, 16, 3))
        raise HeadforgeError("boom")

    with pytest.raises(HeadforgeError, match="boom"):
        write_mp4(tmp_path / "v.mp4", frames())
    assert not (tmp_path / "v.mp4").exists() and not list(tmp_path.glob("*.partial*"))
    with pytest.raises(HeadforgeError, match="no frames"):
        write_mp4(tmp_path / "w.mp4", [])
    with pytest.raises(HeadforgeError, match="frame 1 is"):
        write_mp4(tmp_path / "x.mp4", [np.zeros((16, 16, 3)), np.zeros((8, 8, 3))])


def test_png_writer(tmp_path):
    from PIL import Image

    write_png(tmp_path / "a.png", np.linspace(0, 1, 12).reshape(2, 2, 3))
    assert np.asarray(Image.open(tmp_path / "a.png")).shape == (2, 2, 3)


def test_turntable_command(open_head, tmp_path):
    out = tmp_path / "tt.mp4"
    result = CliRunner().invoke(app, ["render", "turntable", "--model", "open-head", "-o", str(out),
                                      "--frames", "3", "--resolution", "64", "--points", "5000"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["frames"] == 3 and out.is_file() and out.with_suffix(".png").is_file()
    with av.open(str(out)) as container:
        frame = next(container.decode(video=0)).to_ndarray(format="rgb24")
    assert frame.shape == (64, 128, 3)
    left, right = frame[:, :64].astype(float), frame[:, 64:].astype(float)
    background = np.array([237, 237, 242])
    assert (np.abs(left - background).sum(-1) > 30).mean() > 0.15  # the shaded head is there
    assert (np.abs(right - background).sum(-1) > 30).mean() > 0.15  # and the points
