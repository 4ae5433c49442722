"""ARKit blendshape recordings in Live Link Face's CSV layout, as driving sequences.

A row per frame: ``Timecode`` (``HH:MM:SS:FF.fff``: frame FF of the second, with a fraction),
``BlendShapeCount``, the 52 ARKit blendshape weights in [0, 1] under their names in any case
(``EyeBlinkLeft`` or ``eyeBlinkLeft``; "Left" is the subject's left, as ARKit and open-head
name them), and optionally ``HeadYaw``, ``HeadPitch``, ``HeadRoll``, ``LeftEyeYaw``,
``LeftEyePitch``, ``LeftEyeRoll``, ``RightEyeYaw``, ``RightEyePitch``, ``RightEyeRoll`` read as
radians. Rotations become axis-angle poses in the canonical head space (y up, face toward +z):
yaw about +y (the face turns toward the subject's left), pitch about +x (the face looks down),
roll about +z; composed as R = R_y(yaw) R_x(pitch) R_z(roll).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from headforge.errors import HeadforgeError

ROTATION_COLUMNS = {"head": ("HeadYaw", "HeadPitch", "HeadRoll"),
                    "eye_left": ("LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll"),
                    "eye_right": ("RightEyeYaw", "RightEyePitch", "RightEyeRoll")}
DEFAULT_FPS = 60.0  # Live Link Face's recording rate, when the timecodes do not tell


@dataclass
class ArkitClip:
    """weights (T, E) in the order of ``names`` (the head model's expression names); rotations
    {head, eye_left, eye_right: (T, 3) axis-angle, radians}; fps."""

    names: list[str]
    weights: np.ndarray
    rotations: dict[str, np.ndarray]
    fps: float


def euler_to_rotvec(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(T,) yaw, pitch, roll (radians) -> (T, 3) axis-angle of R_y(yaw) R_x(pitch) R_z(roll)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("YXZ", np.stack([yaw, pitch, roll], 1)).as_rotvec()


def _timecode_seconds(text: str) -> tuple[int, float]:
    """``HH:MM:SS:FF.fff`` -> (whole seconds, frame number with its fraction)."""
    parts = text.strip().split(":")
    if len(parts) != 4:
        raise ValueError(text)
    h, m, s = (int(p) for p in parts[:3])
    return 3600 * h + 60 * m + s, float(parts[3])


def estimate_fps(timecodes: list[str]) -> float:
    """The recording rate: the most rows that share one second of timecode (whole seconds
    inside the clip), else :data:`DEFAULT_FPS`."""
    try:
        seconds = [_timecode_seconds(t)[0] for t in timecodes]
    except ValueError:
        return DEFAULT_FPS
    counts = np.unique(seconds, return_counts=True)[1]
    inner = counts[1:-1]
    return float(inner.max()) if len(inner) else DEFAULT_FPS


def read_arkit_csv(path: str | Path, expression_names: list[str]) -> ArkitClip:
    """Read a Live Link Face–style CSV for a head model whose expressions are ``expression_names``
    (open-head: the 52 ARKit names). Every expression must have a column; missing rotation
    columns are zero."""
    path = Path(path)
    if not path.is_file():
        raise HeadforgeError(f"driving CSV {path} does not exist")
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise HeadforgeError(f"cannot read {path} as CSV: {exc}") from None
    if len(rows) < 2:
        raise HeadforgeError(f"{path} has no frames (a header line and one row per frame expected)")
    header = [h.strip() for h in rows[0]]
    column = {h.lower(): i for i, h in enumerate(header)}
    missing = [n for n in expression_names if n.lower() not in column]
    if missing:
        raise HeadforgeError(f"{path} lacks {len(missing)} of the head model's {len(expression_names)} expressions "
                             f"(e.g. {missing[0]!r}): a Live Link Face CSV of the 52 ARKit blendshapes is expected")
    body = [r for r in rows[1:] if any(c.strip() for c in r)]

    def numbers(name: str) -> np.ndarray:
        i = column[name.lower()]
        try:
            return np.array([float(r[i]) for r in body])
        except (ValueError, IndexError):
            raise HeadforgeError(f"{path}: column {header[i]!r} has a missing or non-numeric value") from None

    weights = np.stack([numbers(n) for n in expression_names], 1)
    rotations = {}
    for key, names in ROTATION_COLUMNS.items():
        yaw, pitch, roll = (numbers(n) if n.lower() in column else np.zeros(len(body)) for n in names)
        rotations[key] = euler_to_rotvec(yaw, pitch, roll)
    timecodes = [r[column["timecode"]] for r in body] if "timecode" in column else []
    return ArkitClip(list(expression_names), weights, rotations, estimate_fps(timecodes) if timecodes else DEFAULT_FPS)


def write_arkit_csv(path: str | Path, names: list[str], weights: np.ndarray, head: np.ndarray | None = None,
                    fps: int = 60) -> Path:
    """Write a Live Link Face–style CSV: weights (T, E) under ``names`` (first letter capitalised,
    as the app writes them), head (T, 3) yaw, pitch, roll in radians (zero when None), eyes zero,
    timecodes at ``fps``. For tests and examples."""
    T = len(weights)
    head = np.zeros((T, 3)) if head is None else np.asarray(head)
    header = ["Timecode", "BlendShapeCount"] + [n[0].upper() + n[1:] for n in names]
    header += [c for cols in ROTATION_COLUMNS.values() for c in cols]
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    with tmp.open("w", newline="") as f:
        out = csv.writer(f)
        out.writerow(header)
        for t in range(T):
            s, frame = divmod(t, fps)
            code = f"00:00:{s:02d}:{frame:02d}.000"
            out.writerow([code, len(names), *[f"{w:.6f}" for w in weights[t]], *[f"{v:.6f}" for v in head[t]],
                          *["0"] * 6])
    tmp.replace(path)
    return path
