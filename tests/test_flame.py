"""FLAME loader: a synthetic file with FLAME's exact keys, shapes and dtypes, pickled the way
FLAME's are (protocol 2, chumpy objects), and a crafted pickle that must not run."""

from __future__ import annotations

import pickle
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse
import torch

from headforge.errors import HeadforgeError
from headforge.head.flame import load_flame, restricted_load
from headforge.head.model import HeadModel

V, F = 5023, 9976


@pytest.fixture
def fake_chumpy(monkeypatch):
    """A stand-in 'chumpy.ch' module so pickles reference chumpy.ch.Ch as FLAME's do."""
    chumpy = types.ModuleType("chumpy")
    ch = types.ModuleType("chumpy.ch")

    class Ch:  # pickled with protocol 2 as NEWOBJ + state dict holding 'x', like chumpy
        def __init__(self, x):
            self.x = x
            self._dirty_vars = set()

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    ch.Ch = Ch
    chumpy.ch = ch
    monkeypatch.setitem(sys.modules, "chumpy", chumpy)
    monkeypatch.setitem(sys.modules, "chumpy.ch", ch)
    return Ch


def write_flame(folder: Path, Ch, rng=np.random.default_rng(0)) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    v_template = rng.normal(0, 0.1, (V, 3))
    weights = rng.random((V, 5))
    weights /= weights.sum(1, keepdims=True)
    j_reg = scipy.sparse.random(5, V, density=0.01, format="csc", random_state=0)
    j_reg = scipy.sparse.csc_matrix(j_reg.multiply(1.0 / j_reg.sum(axis=1)))
    model = {
        "v_template": v_template,
        "f": rng.integers(0, V, (F, 3)).astype(np.uint32),
        "shapedirs": Ch(rng.normal(0, 1e-3, (V, 3, 400))),
        "posedirs": rng.normal(0, 1e-4, (V, 3, 36)),
        "J_regressor": j_reg,
        "weights": weights,
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
        "J": rng.normal(0, 0.05, (5, 3)),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }
    (folder / "generic_model.pkl").write_bytes(pickle.dumps(model, protocol=2))
    emb = {"static_lmk_faces_idx": rng.integers(0, F, 51), "static_lmk_bary_coords": np.full((51, 3), 1 / 3),
           "full_lmk_faces_idx": rng.integers(0, F, (1, 68)), "full_lmk_bary_coords": np.full((1, 68, 3), 1 / 3)}
    np.save(folder / "landmark_embedding.npy", np.array(emb, dtype=object), allow_pickle=True)
    masks = {k: rng.choice(V, 50, replace=False) for k in
             ("face", "scalp", "neck", "lips", "left_ear", "right_ear", "left_eyeball", "right_eyeball",
              "nose", "forehead", "boundary", "eye_region")}
    (folder / "FLAME_masks.pkl").write_bytes(pickle.dumps(masks, protocol=2))
    return model


def test_flame_round_trip(tmp_path, fake_chumpy):
    original = write_flame(tmp_path / "flame", fake_chumpy)
    data = load_flame(tmp_path / "flame", n_shape=300, n_expr=100)
    assert data.v_template.shape == (V, 3) and data.faces.shape == (F, 3)
    np.testing.assert_array_equal(data.shapedirs, original["shapedirs"].x[:, :, :300])
    np.testing.assert_array_equal(data.exprdirs, original["shapedirs"].x[:, :, 300:])
    np.testing.assert_array_equal(data.j_regressor, original["J_regressor"].toarray())
    np.testing.assert_array_equal(data.parents, [-1, 0, 1, 1, 1])
    assert data.landmark_faces.shape == (68,) and data.meta["landmarks"]["kind"] == "ibug-68"
    assert {"face", "scalp", "neck", "ears", "eyeballs", "lips"} <= set(data.regions)
    model = HeadModel(data)
    out = model(shape=torch.randn(2, 300), expression=torch.randn(2, 100), jaw_pose=torch.full((2, 3), 0.1))
    assert out.vertices.shape == (2, V, 3) and out.landmarks.shape == (2, 68, 3)
    assert model.posedirs is not None and torch.isfinite(out.vertices).all()


def test_flame_from_environment_variable(tmp_path, fake_chumpy, monkeypatch):
    write_flame(tmp_path / "f", fake_chumpy)
    monkeypatch.setenv("HEADFORGE_FLAME_DIR", str(tmp_path / "f"))
    from headforge.head import create

    assert create("flame").n_shape == 300


def test_missing_flame_says_where_to_get_it(tmp_path, monkeypatch):
    monkeypatch.delenv("HEADFORGE_FLAME_DIR", raising=False)
    with pytest.raises(HeadforgeError, match="licence-gated.*--flame-dir"):
        load_flame(None)
    with pytest.raises(HeadforgeError, match="generic_model.pkl not found"):
        load_flame(tmp_path)


def test_not_a_flame_file(tmp_path):
    (tmp_path / "generic_model.pkl").write_bytes(b"\x00garbage")
    with pytest.raises(HeadforgeError, match="not a readable pickle"):
        load_flame(tmp_path)
    (tmp_path / "generic_model.pkl").write_bytes(pickle.dumps({"v_template": np.zeros((3, 3))}, protocol=2))
    with pytest.raises(HeadforgeError, match="missing f, shapedirs"):
        load_flame(tmp_path)


def test_mismatched_flame_shapes(tmp_path, fake_chumpy):
    write_flame(tmp_path, fake_chumpy)
    raw = pickle.loads((tmp_path / "generic_model.pkl").read_bytes())
    raw["weights"] = raw["weights"][:100]
    (tmp_path / "generic_model.pkl").write_bytes(pickle.dumps(raw, protocol=2))
    with pytest.raises(HeadforgeError, match="weights must be"):
        load_flame(tmp_path)


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


def test_crafted_pickle_is_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps({"v_template": _Evil(marker)}, protocol=2)
    (tmp_path / "generic_model.pkl").write_bytes(payload)
    with pytest.raises(HeadforgeError, match="refusing to load (posix|os|nt).system"):
        load_flame(tmp_path)
    assert not marker.exists()
    with pytest.raises(HeadforgeError, match="refusing to load builtins.eval"):
        restricted_load(b"cbuiltins\neval\n(S'1+1'\ntR.", "test")


def test_crafted_landmark_npy_is_refused(tmp_path, fake_chumpy):
    write_flame(tmp_path, fake_chumpy)
    marker = tmp_path / "pwned2"
    np.save(tmp_path / "landmark_embedding.npy", np.array(_Evil(marker), dtype=object), allow_pickle=True)
    with pytest.raises(HeadforgeError, match="refusing to load"):
        load_flame(tmp_path)
    assert not marker.exists()
