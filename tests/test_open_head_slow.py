"""Slow checks of the open-head build (minutes): run with `pytest -m slow`."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow


def test_anny_still_drops_the_right_eyeball_without_the_fix():
    """If anny fixes its head topology, this fails and the workaround can go."""
    from headforge.head.open_head import _segment_vertices, build_anny_head

    plain = build_anny_head(fix_right_eyeball=False)
    fixed = build_anny_head(fix_right_eyeball=True)
    assert len(_segment_vertices(plain, ["eye_back.R"])) == 0
    assert len(_segment_vertices(fixed, ["eye_back.R"])) == len(_segment_vertices(fixed, ["eye_back.L"])) > 0
    assert len(fixed.faces) > len(plain.faces)


def test_build_is_deterministic():
    from headforge.head.open_head import OpenHeadRecipe, build_open_head

    recipe = OpenHeadRecipe(n_samples=300)
    a, b = build_open_head(recipe), build_open_head(recipe)
    for key in ("v_template", "shapedirs", "exprdirs", "j_regressor", "weights"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert all(np.array_equal(a.regions[k], b.regions[k]) for k in a.regions)


def test_compiled_model_equals_eager_reference():
    """torch.compile (Inductor C++ kernels) is the fast path; the eager module is the reference."""
    import torch

    from conftest import tiny_head_data
    from headforge.head.model import HeadModel

    model = HeadModel(tiny_head_data())
    compiled = torch.compile(model)
    kwargs = dict(shape=torch.randn(4, 4), expression=torch.randn(4, 3), neck_pose=0.3 * torch.randn(4, 3),
                  jaw_pose=0.2 * torch.randn(4, 3), translation=torch.randn(4, 3))
    with torch.no_grad():
        fast, ref = compiled(**kwargs), model(**kwargs)
    torch.testing.assert_close(fast.vertices, ref.vertices, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(fast.landmarks, ref.landmarks, atol=1e-5, rtol=1e-5)
