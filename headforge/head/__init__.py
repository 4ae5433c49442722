"""Parametric head models: one interface (:class:`HeadModel`), two sources of data."""

from headforge.head.model import JOINT_NAMES, HeadModel, HeadModelData, HeadOutput

__all__ = ["JOINT_NAMES", "HeadModel", "HeadModelData", "HeadOutput", "create", "load_data", "MODEL_NAMES"]

MODEL_NAMES = ("open-head", "flame")


def load_data(name: str = "open-head", flame_dir: str | None = None, progress=None) -> HeadModelData:
    """Static data of a named head model. ``flame`` reads the user's own FLAME files."""
    from headforge.errors import HeadforgeError

    if name == "open-head":
        from headforge.head.open_head import load_open_head

        return load_open_head(progress=progress)
    if name == "flame":
        from headforge.head.flame import load_flame

        return load_flame(flame_dir)
    raise HeadforgeError(f"unknown head model {name!r}; choose one of {', '.join(MODEL_NAMES)}")


def create(name: str = "open-head", flame_dir: str | None = None, joint_limits: bool = False,
           progress=None) -> HeadModel:
    """Build a :class:`HeadModel` by name (smplx-style factory)."""
    return HeadModel(load_data(name, flame_dir, progress=progress), joint_limits=joint_limits)
