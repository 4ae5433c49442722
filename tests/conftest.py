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


def tiny_nha_head_data(seed: int = 0):
    """:func:`tiny_head_data` on a finer sphere (V=626, open at the bottom) with what NHA's template reads: named
    regions (face, scalp, neck, lower_neck, lips, eyeballs) and a fixed 478-point "MediaPipe"
    landmark embedding on the front. Built from fixed arrays and a seeded generator only, so
    it is the same on every machine (the open-head build is not bit-identical between builds)."""
    from dataclasses import replace

    base = tiny_head_data(seed, with_posedirs=False)
    rng = np.random.default_rng(seed + 1)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    sphere.update_faces(sphere.triangles_center[:, 1] > -0.095)  # an open neck at the bottom, as a head model has
    sphere.remove_unreferenced_vertices()
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces, np.int64)
    V = len(v)
    # skinning of the coarse sphere carried to the fine one by nearest coarse vertex
    near = np.argmin(np.linalg.norm(v[:, None] - base.v_template[None], axis=-1), axis=1)
    front = np.nonzero((v[f].mean(1)[:, 2] > 0.04) & (np.abs(v[f].mean(1)[:, 1]) < 0.07))[0]
    regions = {"face": np.nonzero((v[:, 2] > 0.03) & (v[:, 1] > -0.07))[0],
               "scalp": np.nonzero((v[:, 2] <= 0.03) & (v[:, 1] > -0.05))[0],
               "neck": np.nonzero(v[:, 1] <= -0.07)[0], "lower_neck": np.nonzero(v[:, 1] < -0.09)[0],
               "lips": np.nonzero((v[:, 2] > 0.06) & (np.abs(v[:, 1] + 0.04) < 0.01))[0],
               "eyeballs": base.regions["eyeballs"][:0]}
    joints = base.j_regressor @ base.v_template
    regressor = np.zeros((5, V))
    for j in range(5):
        regressor[j, np.argsort(np.linalg.norm(v - joints[j], axis=1))[:8]] = 1 / 8
    data = replace(base, name="tiny-nha", v_template=v, faces=f, uv_faces=f.copy(),
                   uvs=np.stack([0.5 + np.arctan2(v[:, 0], v[:, 2]) / (2 * np.pi), 0.5 + v[:, 1] / 0.2], 1),
                   shapedirs=rng.normal(0, 0.003, (V, 3, 4)),
                   exprdirs=rng.normal(0, 0.002, (V, 3, 3)) * (v[:, 1] < -0.03)[:, None, None],
                   j_regressor=regressor, weights=base.weights[near], posedirs=None,
                   landmark_faces=rng.choice(front, 478), landmark_bary=rng.dirichlet(np.ones(3), 478),
                   regions=regions)
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
    from headforge.bench import synthetic as S

    out = tmp_path_factory.mktemp("synth") / "bench"
    config = S.SynthConfig(subjects=1, train_frames=10, val_frames=6, resolution=224, supersample=1, gt_every=2,
                           novel_yaws=(20.0,))
    report = S.synthesize(out, config, log=lambda m: None)
    return out, config, report


@pytest.fixture(scope="session")
def open_head_nha_run(tmp_path_factory, open_head_data):
    """A tiny NHA run folder on open-head (its 52 ARKit expressions, 5 joints): a few iterations at
    64 px on a dataset rendered from the model (:func:`write_rendered_dataset`, no MediaPipe)."""
    from headforge.avatars.engine import fit
    from headforge.avatars.nha.config import NHAConfig

    root = tmp_path_factory.mktemp("open_head_nha")
    data = write_rendered_dataset(root / "data", open_head_data, frames=6, val=2, resolution=96)
    config = NHAConfig.quick()
    for k, v in {"resolution": 64, "subdivide": False, "geometry_iters": 3, "texture_iters": 3, "joint_iters": 2,
                 "align_steps": 1, "val_every": 8, "val_frames": 1, "val_tto_steps": 1, "tto_steps": 1,
                 "checkpoint_every": 8, "tex_grid": 32, "geo_width": 32, "tex_width": 32, "tex_channels": 8,
                 "tex_layers": 2}.items():
        setattr(config, k, v)
    fit("nha", data, root / "run", config, log=lambda m: None)
    return root / "run"


@pytest.fixture
def tiny_head(monkeypatch):
    """``load_data("tiny-nha")`` gives the fixed tiny NHA head (:func:`tiny_nha_head_data`)."""
    import headforge.head

    data = tiny_nha_head_data()
    original = headforge.head.load_data
    monkeypatch.setattr(headforge.head, "load_data",
                        lambda name="open-head", *a, **k: data if name == data.name else original(name, *a, **k))
    return data


@pytest.fixture
def rendered(tmp_path, tiny_head):
    """A tiny dataset rendered from the tiny NHA head (:func:`write_rendered_dataset`)."""
    return write_rendered_dataset(tmp_path / "data", tiny_head)


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


def write_rendered_dataset(root: Path, data, frames: int = 8, val: int = 3, resolution: int = 96, seed: int = 0) -> Path:
    """A tiny headforge dataset rendered from the head model ``data`` with known parameters,
    without MediaPipe (deterministic on a host): normal-shaded crops, coverage masks and the
    model's own landmarks as the detections. The head turns and talks a little; camera OpenCV
    at the origin, head at about 0.6 m."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the same floats whatever the caller's thread count
    try:
        return _write_rendered_dataset(root, data, frames, val, resolution, seed)
    finally:
        torch.set_num_threads(threads)


def _write_rendered_dataset(root: Path, data, frames: int, val: int, resolution: int, seed: int) -> Path:
    import json

    import torch
    from PIL import Image
    from safetensors.torch import save_file

    from headforge.head.model import HeadModel
    from headforge.render import mesh
    from headforge.render.camera import Cameras

    root.mkdir(parents=True, exist_ok=True)
    (root / "frames").mkdir(exist_ok=True)
    (root / "masks").mkdir(exist_ok=True)
    head = HeadModel(data)
    g = torch.Generator().manual_seed(seed)
    T = frames
    phase = torch.linspace(0, 2 * np.pi, T)[:, None]
    with torch.no_grad():
        centre = head().vertices[0].mean(0)
    flip = torch.tensor([1.0, -1.0, -1.0])
    tracked = {"shape": 0.5 * torch.randn(1, head.n_shape, generator=g),
               "expression": 0.3 * torch.sin(phase + torch.arange(head.n_expr)) * (torch.arange(head.n_expr) < 8),
               "root_pose": torch.cat([0.05 * torch.sin(phase), 0.2 * torch.sin(phase), torch.zeros(T, 1)], 1),
               "neck_pose": torch.zeros(T, 3), "jaw_pose": torch.cat([0.1 + 0.1 * torch.sin(phase), torch.zeros(T, 2)], 1),
               "eye_left_pose": torch.zeros(T, 3), "eye_right_pose": torch.zeros(T, 3),
               "translation": (-centre * flip + torch.tensor([0.0, 0.0, 0.6])).expand(T, 3).clone()}
    focal = 2.4 * resolution
    K = torch.tensor([[focal, 0, (resolution - 1) / 2], [0, focal, (resolution - 1) / 2], [0, 0, 1.0]])
    with torch.no_grad():
        out = head(shape=tracked["shape"].expand(T, -1), **{k: v for k, v in tracked.items() if k not in ("shape", "translation")})
        verts = out.vertices * flip + tracked["translation"][:, None]
        lmk = out.landmarks * flip + tracked["translation"][:, None]
        cams = Cameras(K.expand(T, 3, 3), torch.eye(3).expand(T, 3, 3), torch.zeros(T, 3), resolution, resolution)
        frags = mesh.rasterize(cams, verts, head.faces)
        from headforge.head.topology import vertex_normals

        normals = mesh.interpolate(vertex_normals(verts, head.faces), frags, head.faces)
        shade = (0.3 + 0.6 * (-normals[..., 2:]).clamp(min=0)) * torch.tensor([0.9, 0.7, 0.6])
        hit = frags.face_id >= 0
        rgb = torch.where(hit[..., None], shade, torch.ones(3))
    tracked["landmarks"] = (lmk[..., :2] / lmk[..., 2:] * focal + K[:2, 2]).float()
    tracked["valid"] = torch.ones(T, dtype=torch.bool)
    records = []
    for t in range(T):
        Image.fromarray((rgb[t].numpy() * 255).round().astype(np.uint8)).save(root / "frames" / f"{t:05d}.png")
        Image.fromarray(hit[t].numpy().astype(np.uint8) * 255).save(root / "masks" / f"{t:05d}.png")
        records.append({"index": t, "source_frame": t, "valid": True, "split": "val" if t >= T - val else "train",
                        "image": f"frames/{t:05d}.png", "mask": f"masks/{t:05d}.png",
                        "crop": [resolution / 2, resolution / 2, resolution]})
    save_file({k: v.contiguous() for k, v in tracked.items()}, str(root / "tracking.safetensors"))
    meta = {"format": "headforge-dataset", "version": 1, "model": data.name, "n_shape": head.n_shape,
            "expression_names": list(data.expression_names), "resolution": resolution, "fps": 25.0,
            "intrinsics": K.tolist(), "camera": "OpenCV pinhole at the origin", "frames": records}
    (root / "dataset.json").write_text(json.dumps(meta))
    return root
