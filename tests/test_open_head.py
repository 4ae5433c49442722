"""open-head: the recipe, the anny workaround, the landmark embedding, the CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from headforge.cli import app
from headforge.head import landmarks
from headforge.head.open_head import ANNY_TO_HF, OpenHeadRecipe, _anny_right_eyeball_fix


def test_anny_cache_is_bypassed_and_restored():
    import anny.models.full_model as full_model
    import anny.paths

    before = (anny.paths.get_anny_cache_path(), full_model._faces_to_keep_from_submodel)
    with _anny_right_eyeball_fix():
        assert anny.paths.get_anny_cache_path() is None
        assert full_model._faces_to_keep_from_submodel is not before[1]
    assert (anny.paths.get_anny_cache_path(), full_model._faces_to_keep_from_submodel) == before


def test_axis_conversion_is_a_rotation():
    assert np.isclose(np.linalg.det(ANNY_TO_HF), 1.0)
    np.testing.assert_allclose(ANNY_TO_HF @ [0, -1, 0], [0, 0, 1])  # anny's face direction -> +z
    np.testing.assert_allclose(ANNY_TO_HF @ [0, 0, 1], [0, 1, 0])  # anny's up -> +y


def test_recipe_digest_names_the_cache():
    """The cache file is named by a digest of every recipe field, the same in any interpreter
    (nothing process-dependent, e.g. hash randomisation, goes into it)."""
    from dataclasses import fields, replace

    from headforge.head.open_head import cache_path

    recipe = OpenHeadRecipe()
    digest = recipe.digest()
    assert len(digest) == 12 and int(digest, 16) >= 0
    code = "from headforge.head.open_head import OpenHeadRecipe; print(OpenHeadRecipe().digest())"
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env={**__import__("os").environ, "PYTHONHASHSEED": "12345"})
    assert other.returncode == 0 and other.stdout.strip() == digest, other.stderr
    changed = {int: lambda v: v + 1, float: lambda v: v * 1.5 + 0.1, str: lambda v: v + ".post1",
               tuple: lambda v: tuple(x + 0.05 for x in v)}
    for field in fields(OpenHeadRecipe):
        value = getattr(recipe, field.name)
        other = replace(recipe, **{field.name: changed[type(value)](value)})
        assert other.digest() != digest, field.name
        assert cache_path(other) != cache_path(recipe), field.name
    assert cache_path(recipe).name == f"open-head-v{recipe.recipe_version}-{digest}.safetensors"


def test_open_head_contents(open_head_data, open_head):
    d = open_head_data
    assert d.shapedirs.shape[2] == 100 and d.meta["shape_variance_explained_50"] > 0.99
    assert len(d.expression_names) == 52 and {"jawOpen", "eyeBlinkLeft", "tongueOut"} <= set(d.expression_names)
    for region in ("face", "scalp", "neck", "lower_neck", "ears", "eyeballs", "lips", "mouth_interior"):
        assert len(d.regions[region]) > 0, region
    np.testing.assert_allclose(d.weights.sum(1), 1.0, atol=1e-9)
    # y up, face toward +z, subject's left eye at +x, origin between the eyes
    t = d.v_template
    left = t[d.regions["eyeball_left"]].mean(0)
    right = t[d.regions["eyeball_right"]].mean(0)
    assert left[0] > 0.02 and right[0] < -0.02 and abs(left[1] - right[1]) < 1e-3
    nose_tip = open_head().landmarks[0, 1]
    assert nose_tip[2] > left[2]  # the nose is in front of the eyes
    assert t[:, 1].max() > 0.08 and t[:, 1].min() < -0.1  # head top above, neck below
    assert np.linalg.norm(0.5 * (left + right)) < 3e-3
    # blinking closes the eyelids: upper and lower lid landmarks get closer
    blink = torch.zeros(1, 52)
    blink[0, [d.expression_names.index("eyeBlinkLeft"), d.expression_names.index("eyeBlinkRight")]] = 1.0
    gap = lambda out: (out.landmarks[0, landmarks.EYELID_PAIRS[:, 0]] - out.landmarks[0, landmarks.EYELID_PAIRS[:, 1]]).norm(dim=-1)  # noqa: E731
    # (measured: 8.8 mm open -> 3.6 mm closed on average; lid points sit just off the margins)
    assert gap(open_head(expression=blink)).mean() < 0.5 * gap(open_head()).mean()


def test_landmark_embedding_quality_measured(open_head_data):
    """MediaPipe on 27 held-out renders (3 identities x 3 expressions x 3 views) at 256 px
    against the projected embedded landmarks (about 6 s). Measured 1.45 px median (2.82 px at
    the build's 512 px); the bound, 1.8 px, is 3.6 px at 512."""
    from headforge.head.landmarks import evaluate_embedding

    meta = open_head_data.meta["landmarks"]
    assert meta["kind"] == "mediapipe-478" and len(meta["mediapipe_to_ibug68"]) == 68
    error = evaluate_embedding(open_head_data, resolution=256)
    assert error["renders_used"] >= 0.8 * error["renders_tested"] == 0.8 * 27
    assert error["landmark_median_px"] < 1.8, error
    assert error["landmark_median_px_inner"] < error["landmark_p90_px"]


@pytest.mark.slow
def test_landmark_embedding_figure_recorded_by_the_build_is_reproduced(open_head_data):
    """The build records the held-out median at 512 px (what ``headforge model info`` reports):
    measuring it again gives the same figure (2.82 px on the hosts of 2026-12; about 30 s)."""
    from headforge.head.landmarks import evaluate_embedding

    recorded = open_head_data.meta["landmarks"]["heldout"]["landmark_median_px"]
    error = evaluate_embedding(open_head_data, resolution=512)
    assert error["landmark_median_px"] == pytest.approx(recorded, abs=0.05) and error["landmark_median_px"] < 3.5


def test_ibug68_subset_is_anatomically_ordered(open_head):
    lmk = open_head().landmarks[0][torch.as_tensor(landmarks.MEDIAPIPE_TO_IBUG68)]
    assert lmk[0, 0] < 0 < lmk[16, 0]  # jaw runs from the subject's right (-x) to left (+x)
    assert lmk[8, 1] < lmk[30, 1] < lmk[27, 1]  # chin below nose tip below nose bridge
    assert lmk[36, 0] < lmk[39, 0] < 0 < lmk[42, 0] < lmk[45, 0]  # eye corners


def test_model_info_json():
    result = CliRunner().invoke(app, ["model", "info", "--model", "open-head", "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout.strip().splitlines()[-1])
    for key in ("vertices", "faces", "joints", "n_shape", "n_expr", "expression_names",
                "shape_variance_explained", "landmarks"):
        assert key in info
    assert info["landmarks"] == 478 and info["joints"] == 5 and info["n_expr"] == 52


@pytest.mark.parametrize("args, message", [
    (["model", "info", "--model", "nope"], "unknown head model 'nope'"),
    (["model", "info", "--model", "flame", "--flame-dir", "/nonexistent"], "generic_model.pkl not found"),
    (["model", "fit-image", "/nonexistent.jpg", "-o", "x.png"], "image not found"),
])
def test_cli_errors_are_one_line(args, message, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "headforge.cli", *args], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 1
    assert message in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "x.png").exists()


def test_fit_image_grace_hopper(open_head, tmp_path):
    import matplotlib.cbook
    from PIL import Image

    from headforge.head.fit import ImageFitConfig, fit_image, overlay

    photo = matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    pixels = np.asarray(Image.open(photo).convert("RGB"))
    fit = fit_image(open_head, pixels, ImageFitConfig.quick())
    assert fit.median_px < 3.0  # measured 1.1 px with 300 steps
    image = overlay(pixels, fit, open_head.faces.numpy())
    assert image.shape == pixels.shape and image.dtype == np.uint8


def test_fit_image_rejects_faceless_image(open_head):
    from headforge.errors import HeadforgeError
    from headforge.head.fit import fit_image

    with pytest.raises(HeadforgeError, match="no face found"):
        fit_image(open_head, np.full((256, 256, 3), 128, np.uint8))


def test_fit_video_frame(talking_bun, tmp_path):
    """Fit a frame of the real phone clip through the CLI (frame read from ../shared)."""
    out = tmp_path / "bun.png"
    result = CliRunner().invoke(app, ["model", "fit-image", str(talking_bun), "--frame", "30", "-o", str(out), "--steps", "150"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert out.is_file() and summary["landmark_median_px"] < 3.0


def test_bad_videos(tmp_path):
    from headforge.data.video import read_frame
    from headforge.errors import HeadforgeError

    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(HeadforgeError, match="empty"):
        read_frame(empty)
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"this is not a video" * 100)
    with pytest.raises(HeadforgeError, match="cannot decode video"):
        read_frame(junk)
