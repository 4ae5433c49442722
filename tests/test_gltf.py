"""The animatable glTF export: the writer's skinning, morphing and animation reproduce the head
model exactly (evaluated from the file with numpy), the file round-trips through pygltflib and
trimesh, and a trained NHA exports with 52 ARKit morph targets, a skin and its own frames."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from headforge.errors import HeadforgeError

pygltflib = pytest.importorskip("pygltflib", reason="pygltflib is a dev dependency (pip install -e '.[dev]')")


def accessor(g, index: int) -> np.ndarray:
    """An accessor's data (count, components) from a loaded GLB."""
    a = g.accessors[index]
    view = g.bufferViews[a.bufferView]
    blob = g.binary_blob()
    dtype = {5126: "<f4", 5121: "u1", 5123: "<u2", 5125: "<u4"}[a.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
    start = view.byteOffset + (a.byteOffset or 0)
    return np.frombuffer(blob, dtype, a.count * width, start).reshape(a.count, width).astype(np.float64)


def pose_from_file(g, t: int) -> np.ndarray:
    """The skinned, morphed vertices (V, 3) of animation frame ``t`` in glTF world, computed from
    the file alone: morph weights, joint TRS (rest translations, animated rotations), the head
    node's animated translation, inverse bind matrices and the four joint weights per vertex."""
    from scipy.spatial.transform import Rotation

    prim = g.meshes[0].primitives[0]
    pos = accessor(g, prim.attributes.POSITION)
    anim = g.animations[0]
    values = {(c.target.node, c.target.path): accessor(g, anim.samplers[c.sampler].output) for c in anim.channels}
    mesh_node = next(i for i, n in enumerate(g.nodes) if n.mesh is not None)
    E = len(prim.targets)
    weights = values[(mesh_node, "weights")].reshape(-1, E)[t]
    pos = pos + sum(w * accessor(g, tgt["POSITION"] if isinstance(tgt, dict) else tgt.POSITION)
                    for w, tgt in zip(weights, prim.targets))
    parent = {c: i for i, n in enumerate(g.nodes) for c in (n.children or [])}

    def world(i: int) -> np.ndarray:
        n = g.nodes[i]
        m = np.eye(4)
        m[:3, 3] = values.get((i, "translation"), [n.translation or [0, 0, 0]] * (t + 1))[t]
        q = values.get((i, "rotation"))
        if q is not None:
            m[:3, :3] = Rotation.from_quat(q[t]).as_matrix()
        return (world(parent[i]) @ m) if i in parent else m

    skin = g.skins[0]
    ibm = accessor(g, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    joints = np.stack([world(j) @ ibm[k] for k, j in enumerate(skin.joints)])
    ids = accessor(g, prim.attributes.JOINTS_0).astype(int)
    w = accessor(g, prim.attributes.WEIGHTS_0)
    blended = np.einsum("vk,vkij->vij", w, joints[ids])
    return np.einsum("vij,vj->vi", blended[:, :3, :3], pos) + blended[:, :3, 3]


def test_the_glb_skins_morphs_and_animates_as_the_head_model_does(tmp_path):
    """Posed vertices evaluated from the written file equal HeadModel's for random poses,
    expressions and translations (camera -> glTF world), to float32 precision."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import tiny_head_data

    from headforge.export import gltf
    from headforge.head.model import POSE_ARGS, HeadModel
    from headforge.head.pose import head_to_camera

    data = tiny_head_data(with_posedirs=False)
    # glTF's joints cannot move with the expression: keep expressions off the regressed vertices
    data.exprdirs = data.exprdirs * (data.j_regressor.sum(0) == 0)[:, None, None]
    head = HeadModel(data)
    g = torch.Generator().manual_seed(0)
    T = 4
    shape = 0.5 * torch.randn(1, head.n_shape, generator=g)
    params = {k: 0.3 * torch.randn(T, 3, generator=g) for k in POSE_ARGS}
    params["expression"] = torch.randn(T, head.n_expr, generator=g)
    translation = torch.tensor([0.01, -0.02, 0.6]) + 0.01 * torch.randn(T, 3, generator=g)
    with torch.no_grad():
        rest = head(shape=shape)
        posed = head(shape=shape.expand(T, -1), **params)
    cam = head_to_camera(posed.vertices, translation).numpy()
    expected = cam @ gltf.OPENGL_FROM_OPENCV  # OpenCV camera -> OpenGL camera (= glTF world)
    exprdirs = head.blenddirs[head.n_shape:].reshape(head.n_expr, -1, 3).numpy()
    anim = gltf.Animation(25.0, torch.stack([params[k] for k in POSE_ARGS], 1).numpy(),
                          gltf.camera_to_gltf(translation.numpy()), params["expression"].numpy())
    path = gltf.write_glb(tmp_path / "head.glb", rest.vertices[0].numpy(), data.faces, uvs=data.uvs,
                          skin=gltf.Skin(list(head.joint_names), data.parents, rest.joints[0].numpy(), data.weights),
                          morph_targets=exprdirs, target_names=["a", "b", "c"], animation=anim,
                          camera=gltf.Camera(np.diag([300.0, 300.0, 1.0]), 256, 256))
    loaded = pygltflib.GLTF2().load(str(path))
    assert loaded.meshes[0].extras["targetNames"] == ["a", "b", "c"]
    assert [n.name for n in loaded.nodes if n.camera is not None] == ["camera"]
    times = accessor(loaded, loaded.animations[0].samplers[0].input)[:, 0]
    assert np.allclose(times, np.arange(T) / 25.0)
    for t in range(T):
        assert np.abs(pose_from_file(loaded, t) - expected[t]).max() < 2e-6
    import trimesh

    scene = trimesh.load(path)
    assert sum(len(m.vertices) for m in scene.geometry.values()) == len(data.v_template)


def test_the_writer_refuses_inconsistent_arrays(tmp_path):
    from headforge.export import gltf

    v = np.random.default_rng(0).normal(size=(4, 3))
    f = np.array([[0, 1, 2], [0, 2, 3]])
    with pytest.raises(HeadforgeError, match="faces"):
        gltf.write_glb(tmp_path / "a.glb", v, f + 2)
    with pytest.raises(HeadforgeError, match="morph_targets"):
        gltf.write_glb(tmp_path / "a.glb", v, f, morph_targets=np.zeros((2, 5, 3)))
    with pytest.raises(HeadforgeError, match="needs a skin"):
        gltf.write_glb(tmp_path / "a.glb", v, f, animation=gltf.Animation(25, np.zeros((1, 1, 3)), np.zeros((1, 3))))
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_a_trained_nha_exports_an_animatable_glb(open_head_nha_run, tmp_path):
    """``headforge export RUN --format glb``: 52 ARKit morph targets, the five-joint skin, the
    baked texture, the run's own frames as the animation at the dataset's fps; ``--driving
    CSV`` animates it by the recording instead. It loads in trimesh with every triangle."""
    import trimesh
    from typer.testing import CliRunner

    from headforge.avatars.run import load_run
    from headforge.cli import app
    from headforge.data.arkit import write_arkit_csv

    r = load_run(open_head_nha_run)
    names = list(r.avatar.head.expression_names)
    runner = CliRunner()
    res = runner.invoke(app, ["export", str(open_head_nha_run), "-o", str(tmp_path / "own"), "--format", "glb",
                              "--texture-size", "64"])
    assert res.exit_code == 0, res.output
    g = pygltflib.GLTF2().load(str(tmp_path / "own" / "avatar.glb"))
    prim = g.meshes[0].primitives[0]
    assert len(prim.targets) == 52 and g.meshes[0].extras["targetNames"] == names and "jawOpen" in names
    assert [g.nodes[j].name for j in g.skins[0].joints] == ["root", "neck", "jaw", "eye_left", "eye_right"]
    assert g.materials[0].pbrMetallicRoughness.baseColorTexture.index == 0 and len(g.images) == 1
    frames = len(r.assets.rows("all"))
    anim = g.animations[0]
    assert len(anim.channels) == 5 + 1 + 1  # joint rotations, head translation, morph weights
    assert accessor(g, anim.samplers[0].input).shape[0] == frames
    assert anim.extras["fps"] == r.assets.meta["fps"]
    scene = trimesh.load(tmp_path / "own" / "avatar.glb")
    assert sum(len(m.faces) for m in scene.geometry.values()) == len(r.avatar.head.faces)
    # the animation's frame 0 is the avatar's first frame, posed as headforge poses it (camera -> glTF)
    from headforge.export.gltf import OPENGL_FROM_OPENCV

    with torch.no_grad():
        verts = r.avatar.pose(r.avatar.frame_params(torch.tensor(r.assets.rows("all")[:1])))[0][0].numpy()
    from headforge.avatars.nha.export import split_seams

    ids = split_seams(r.avatar.head.faces.numpy(), r.avatar.head.uv_faces.numpy())[0]
    error = np.abs(pose_from_file(g, 0) - verts[ids] @ OPENGL_FROM_OPENCV)
    # NHA's neck offsets depend on the neck pose and joints on the expression: only these differ
    assert np.median(error) < 1e-4 and error.max() < 0.01
    # driven by an ARKit CSV: one animation frame per row, the CSV's weights on the morph targets
    weights = np.zeros((3, 52))
    weights[1, names.index("jawOpen")] = 1.0
    csv = write_arkit_csv(tmp_path / "take.csv", names, weights, fps=30)
    res = runner.invoke(app, ["export", str(open_head_nha_run), "-o", str(tmp_path / "csv"), "--format", "glb",
                              "--texture-size", "16", "--driving", str(csv)])
    assert res.exit_code == 0, res.output
    g = pygltflib.GLTF2().load(str(tmp_path / "csv" / "avatar.glb"))
    mesh_node = next(i for i, n in enumerate(g.nodes) if n.mesh is not None)
    ch = next(c for c in g.animations[0].channels if c.target.node == mesh_node)
    assert np.allclose(accessor(g, g.animations[0].samplers[ch.sampler].output).reshape(3, 52), weights, atol=1e-6)
    assert json.loads(res.stdout.strip().splitlines()[-1])["files"][0].endswith("avatar.glb")
