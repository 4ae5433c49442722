"""Load the user's own FLAME files (FLAME 2020 / 2023) into :class:`HeadModelData`.

FLAME is licence-gated: users register on the FLAME website (flame.is.tue.mpg.de), accept
its licence and download ``generic_model.pkl`` themselves; headforge never ships it. Point
headforge at the folder with ``--flame-dir DIR`` or ``HEADFORGE_FLAME_DIR``.

``generic_model.pkl`` is a Python-2 pickle holding numpy arrays, a scipy CSC matrix and
chumpy objects. A pickle can run arbitrary code when loaded, so it is read with a
restricted unpickler that admits only the numpy reconstruction helpers, and maps chumpy
and scipy.sparse classes to inert stand-ins from which arrays are taken. chumpy is never
imported (it is unmaintained and breaks on current numpy).
"""

from __future__ import annotations

import io
import os
import pickle
from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError
from headforge.head.model import JOINT_NAMES, HeadModelData

FLAME_HELP = ("FLAME files are licence-gated and not shipped with headforge: register on the FLAME "
              "website (flame.is.tue.mpg.de), download FLAME 2020 or 2023, and pass the folder holding "
              "generic_model.pkl with --flame-dir DIR or set HEADFORGE_FLAME_DIR")

FLAME_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")


class _Inert:
    """Stand-in for a chumpy or scipy.sparse object: keeps its pickled state, runs nothing."""

    def __init__(self, *args, **kwargs):
        self.args = args
        self.state = {}

    def __setstate__(self, state):
        self.state = state if isinstance(state, dict) else {"state": state}


class _ChumpyArray(_Inert):
    def to_array(self) -> np.ndarray:
        if "x" in self.state:
            return np.asarray(self.state["x"])
        raise HeadforgeError("unsupported chumpy object in the FLAME file (no 'x' array)")


class _SparseMatrix(_Inert):
    def to_array(self) -> np.ndarray:
        from scipy.sparse import coo_matrix, csc_matrix, csr_matrix

        s = self.state
        shape = tuple(s.get("_shape", s.get("shape", ())))
        if "indptr" in s:
            kind = csr_matrix if self.kind == "csr" else csc_matrix
            return kind((s["data"], s["indices"], s["indptr"]), shape=shape).toarray()
        if "row" in s:
            return coo_matrix((s["data"], (s["row"], s["col"])), shape=shape).toarray()
        raise HeadforgeError("unsupported sparse matrix in the FLAME file")


def _sparse(kind: str):
    return type(f"_{kind}_matrix", (_SparseMatrix,), {"kind": kind})


_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("copyreg", "_reconstructor"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("_codecs", "encode"),  # how Python 3 writes bytes into protocol-2 pickles; pure
}
_ALLOWED_BUILTINS = {"object", "set", "frozenset", "list", "dict", "tuple", "bytearray", "complex", "slice"}


class RestrictedUnpickler(pickle.Unpickler):
    """Admits numpy arrays/dtypes/scalars, maps chumpy and scipy.sparse classes to inert
    stand-ins, and refuses every other global (``os.system``, ``builtins.eval``, ...)."""

    def find_class(self, module: str, name: str):
        module = {"__builtin__": "builtins", "copy_reg": "copyreg"}.get(module, module)  # Python-2 names
        if module.startswith("chumpy"):
            return _ChumpyArray
        if module.startswith("scipy.sparse"):
            for kind in ("csc", "csr", "coo"):
                if name == f"{kind}_matrix" or name == f"{kind}_array":
                    return _sparse(kind)
        if module == "builtins" and name in _ALLOWED_BUILTINS:
            return super().find_class(module, name)
        if (module, name) in _ALLOWED:
            return super().find_class(module, name)
        raise HeadforgeError(f"refusing to load {module}.{name} from a pickle: not a FLAME data type")


def _plain(value):
    """Replace stand-ins by numpy arrays, recursively through dicts."""
    if isinstance(value, (_ChumpyArray, _SparseMatrix)):
        return value.to_array()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def restricted_load(data: bytes, what: str):
    try:
        return _plain(RestrictedUnpickler(io.BytesIO(data), encoding="latin1").load())
    except HeadforgeError as exc:
        raise HeadforgeError(f"{what}: {exc}") from None
    except Exception as exc:
        raise HeadforgeError(f"{what} is not a readable pickle ({type(exc).__name__}: {exc})") from None


def _load_npy_restricted(path: Path):
    """Read a .npy that may hold a pickled object (FLAME's landmark_embedding.npy) safely."""
    with open(path, "rb") as handle:
        try:
            version = np.lib.format.read_magic(handle)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            _, _, dtype = read_header(handle)
        except Exception as exc:
            raise HeadforgeError(f"{path} is not a .npy file ({exc})") from None
        if dtype.hasobject:
            value = restricted_load(handle.read(), str(path))
            return value.item() if isinstance(value, np.ndarray) and value.dtype == object and value.ndim == 0 else value
    return np.load(path, allow_pickle=False)


def find_flame_dir(flame_dir: str | os.PathLike | None) -> Path:
    path = flame_dir or os.environ.get("HEADFORGE_FLAME_DIR")
    if not path:
        raise HeadforgeError(f"no FLAME folder given. {FLAME_HELP}")
    path = Path(path)
    if not (path / "generic_model.pkl").is_file():
        raise HeadforgeError(f"{path / 'generic_model.pkl'} not found. {FLAME_HELP}")
    return path


def _cylindrical_uvs(vertices: np.ndarray) -> np.ndarray:
    """Fallback UVs when FLAME_texture.npz is absent: angle around y, height along y."""
    centre = vertices.mean(0)
    u = (np.arctan2(vertices[:, 0] - centre[0], vertices[:, 2] - centre[2]) / (2 * np.pi)) + 0.5
    y = vertices[:, 1]
    v = (y - y.min()) / max(y.max() - y.min(), 1e-9)
    return np.stack([u, v], axis=1)


def load_flame(flame_dir: str | os.PathLike | None = None, n_shape: int = 300, n_expr: int = 100) -> HeadModelData:
    """Read ``generic_model.pkl`` (+ ``landmark_embedding.npy``, ``FLAME_masks.pkl``,
    ``FLAME_texture.npz`` when present) from the user's FLAME folder."""
    folder = find_flame_dir(flame_dir)
    pkl = folder / "generic_model.pkl"
    raw = restricted_load(pkl.read_bytes(), str(pkl))
    if not isinstance(raw, dict):
        raise HeadforgeError(f"{pkl} does not hold a FLAME model dictionary")
    missing = [k for k in FLAME_KEYS if k not in raw]
    if missing:
        raise HeadforgeError(f"{pkl} is not a FLAME model: missing {', '.join(missing)}")
    v_template = np.asarray(raw["v_template"], np.float64)
    V = v_template.shape[0] if v_template.ndim == 2 else -1
    faces = np.asarray(raw["f"]).astype(np.int64)
    shapedirs = np.asarray(raw["shapedirs"], np.float64)
    if V < 0 or shapedirs.shape[:2] != (V, 3) or shapedirs.shape[2] < 300 + 1:
        raise HeadforgeError(f"{pkl}: shapedirs has shape {shapedirs.shape}, expected ({V}, 3, 300 + n_expr)")
    total_expr = shapedirs.shape[2] - 300
    if not (0 < n_shape <= 300 and 0 < n_expr <= total_expr):
        raise HeadforgeError(f"n_shape must be in 1..300 and n_expr in 1..{total_expr}")
    kintree = np.asarray(raw["kintree_table"]).astype(np.int64)
    parents = kintree[0].copy()
    parents[0] = -1
    if len(parents) != len(JOINT_NAMES):
        raise HeadforgeError(f"{pkl}: {len(parents)} joints, FLAME has {len(JOINT_NAMES)}")
    j_regressor = np.asarray(raw["J_regressor"], np.float64)
    uvs, uv_faces = _cylindrical_uvs(v_template), faces.copy()
    uv_source = "cylindrical (FLAME_texture.npz absent)"
    if (folder / "FLAME_texture.npz").is_file():
        with np.load(folder / "FLAME_texture.npz", allow_pickle=False) as tex:
            if "vt" in tex and "ft" in tex:
                uvs, uv_faces, uv_source = tex["vt"].astype(np.float64), tex["ft"].astype(np.int64), "FLAME_texture.npz"
    data = HeadModelData(
        name="flame", v_template=v_template, faces=faces, uvs=uvs, uv_faces=uv_faces,
        shapedirs=shapedirs[:, :, :n_shape], exprdirs=shapedirs[:, :, 300:300 + n_expr],
        j_regressor=j_regressor, weights=np.asarray(raw["weights"], np.float64), parents=parents,
        posedirs=np.asarray(raw["posedirs"], np.float64),
        expression_names=[f"expr{i:03d}" for i in range(n_expr)],
        meta={"source": f"user FLAME files in {folder} (FLAME licence)", "uv_source": uv_source,
              "shape_variance_explained": None, "expression_range": None})
    _add_landmarks(data, folder)
    _add_masks(data, folder)
    data.validate()
    return data


def _add_landmarks(data: HeadModelData, folder: Path) -> None:
    path = folder / "landmark_embedding.npy"
    if not path.is_file():
        return
    emb = _load_npy_restricted(path)
    if not isinstance(emb, dict):
        raise HeadforgeError(f"{path} does not hold FLAME's landmark dictionary")
    for faces_key, bary_key, kind in (("full_lmk_faces_idx", "full_lmk_bary_coords", "ibug-68"),
                                      ("static_lmk_faces_idx", "static_lmk_bary_coords", "ibug-51-static")):
        if faces_key in emb and bary_key in emb:
            data.landmark_faces = np.asarray(emb[faces_key]).reshape(-1).astype(np.int64)
            data.landmark_bary = np.asarray(emb[bary_key], np.float64).reshape(-1, 3)
            data.meta["landmarks"] = {"kind": kind}
            return
    raise HeadforgeError(f"{path} has none of FLAME's landmark keys")


FLAME_MASK_TO_REGION = {"face": ["face"], "scalp": ["scalp"], "neck": ["neck"], "lips": ["lips"],
                        "ears": ["left_ear", "right_ear"], "eyeballs": ["left_eyeball", "right_eyeball"],
                        "eyeball_left": ["left_eyeball"], "eyeball_right": ["right_eyeball"],
                        "nose": ["nose"], "forehead": ["forehead"], "eye_region": ["eye_region"],
                        "boundary": ["boundary"]}


def _add_masks(data: HeadModelData, folder: Path) -> None:
    path = folder / "FLAME_masks.pkl"
    if not path.is_file():
        return
    masks = restricted_load(path.read_bytes(), str(path))
    if not isinstance(masks, dict):
        raise HeadforgeError(f"{path} does not hold FLAME's mask dictionary")
    for region, keys in FLAME_MASK_TO_REGION.items():
        if all(k in masks for k in keys):
            data.regions[region] = np.unique(np.concatenate([np.asarray(masks[k]).astype(np.int64) for k in keys]))
