"""Shared fixtures: a tiny synthetic head model (fast, exact) and the real open-head."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

os.environ.setdefault("GLOG_minloglevel", "2")
SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def tiny_head_data(seed: int = 0, with_posedirs: bool = True):
    """An icosphere 'head' with FLAME's five joints: root/neck at the bottom, a jaw region
    (lower front), two small eyeball regions. Shapes: V=162, F=320, S=4, E=3."""
    from headforge.head.model import HeadModelData

    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    v = np.asarray(sphere.vertices)
    V = len(v)
    eyes = {3: v[:, 0] > 0.05, 4: v[:, 0] < -0.05}
    eyes = {j: m & (v[:, 2] > 0.06) & (np.abs(v[:, 1]) < 0.04) for j, m in eyes.items()}
    jaw = (v[:, 1] < -0.03) & (v[:, 2] > 0.0)
    weights = np.zeros((V, 5))
    weights[:, 1] = 1.0
    weights[v[:, 1] < -0.07, :2] = [0.5, 0.5]
    weights[jaw] = [0, 0, 1, 0, 0]
    for j, m in eyes.items():
        weights[m] = np.eye(5)[j]
    joints = np.array([[0, -0.12, 0], [0, -0.05, 0], [0, -0.02, 0.02], [0.05, 0.02, 0.06], [-0.05, 0.02, 0.06]])
    regressor = np.zeros((5, V))
    for j in range(5):  # exact joints for the template: one-hot on a virtual vertex is not
        ids = np.argsort(np.linalg.norm(v - joints[j], axis=1))[:8]  # possible, so average 8
        regressor[j, ids] = 1 / 8
    data = HeadModelData(
        name="tiny", v_template=v, faces=np.asarray(sphere.faces, np.int64),
        uvs=np.stack([0.5 + np.arctan2(v[:, 0], v[:, 2]) / (2 * np.pi), 0.5 + v[:, 1] / 0.2], 1),
        uv_faces=np.asarray(sphere.faces, np.int64),
        shapedirs=rng.normal(0, 0.003, (V, 3, 4)), exprdirs=rng.normal(0, 0.002, (V, 3, 3)) * jaw[:, None, None],
        j_regressor=regressor, weights=weights, parents=np.array([-1, 0, 1, 1, 1]),
        posedirs=rng.normal(0, 1e-3, (V, 3, 36)) if with_posedirs else None,
        landmark_faces=np.arange(10), landmark_bary=np.full((10, 3), 1 / 3),
        regions={"jaw": np.nonzero(jaw)[0], "eyeballs": np.nonzero(eyes[3] | eyes[4])[0],
                 "eyeball_left": np.nonzero(eyes[3])[0], "eyeball_right": np.nonzero(eyes[4])[0],
                 "lower_neck": np.nonzero(v[:, 1] < -0.09)[0]},
        expression_names=["a", "b", "c"])
    data.validate()
    return data


@pytest.fixture
def tiny_data():
    return tiny_head_data()


@pytest.fixture(scope="session")
def open_head_data():
    """The real open-head data (built and cached on first use: a few minutes)."""
    from headforge.head.open_head import load_open_head

    return load_open_head()


@pytest.fixture(scope="session")
def open_head(open_head_data):
    from headforge.head.model import HeadModel

    return HeadModel(open_head_data)


@pytest.fixture(scope="session")
def talking_bun():
    path = SHARED / "data" / "video" / "talking_bun.mp4"
    if not path.is_file():
        pytest.skip("../shared/data/video/talking_bun.mp4 is not present")
    return path


@pytest.fixture(scope="session")
def synth_bench(tmp_path_factory, open_head_data):
    """One tiny `headforge synth` subject, rendered and tracked end to end (MediaPipe needs
    faces of ~200 px): (benchmark folder, config, report)."""
    from headforge.data import synthetic as S

    out = tmp_path_factory.mktemp("synth") / "bench"
    config = S.SynthConfig(subjects=1, train_frames=10, val_frames=6, resolution=224, supersample=1, gt_every=2,
                           novel_yaws=(20.0,))
    report = S.synthesize(out, config, log=lambda m: None)
    return out, config, report


@pytest.fixture
def interrupt_after():
    """``interrupt_after(n)``: a training progress callback that raises KeyboardInterrupt on its
    n-th call (a run killed after n - 1 iterations)."""
    def make(n: int):
        calls = {"n": 0}

        def progress():
            calls["n"] += 1
            if calls["n"] == n:
                raise KeyboardInterrupt

        return progress

    return make
