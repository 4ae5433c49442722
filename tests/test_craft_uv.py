"""HeadCraft UV layout, baking, uint16 storage, seam post-processing and lookup on the bare template."""

import numpy as np
import pytest

from headforge.errors import HeadforgeError


@pytest.fixture(scope="module")
def setup():
    from headforge.craft import register as R
    from headforge.craft import uvmap
    from headforge.head.open_head import load_open_head
    from headforge.head.uv import craft_layout

    data = load_open_head()
    template = R.build_template(data, 1)
    layout = craft_layout(data)
    duv = uvmap.dense_uv(layout, 1, data.faces, template.subdivision.faces)
    return data, template, layout, duv


def _field(x):
    return np.stack([0.01 * np.sin(40 * x[:, 1]), 0.005 * np.cos(30 * x[:, 0]), 0.02 * np.clip(x[:, 1], 0, None)], 1)


def test_layout_islands_no_flips_same_density(setup):
    from headforge.head.uv import _uv_area

    data, _, layout, _ = setup
    area = _uv_area(layout.uvs, layout.uv_faces)
    main = layout.island < 2
    assert (area[main] > 0).all(), "face and scalp islands must have no flipped triangles"
    assert abs(layout.meta["density_ratio_face_to_scalp"] - 1) < 0.05
    assert (layout.uvs >= 0).all() and (layout.uvs <= 1).all()
    face_uv = layout.uvs[layout.uv_faces[layout.island == 1]].reshape(-1, 2)
    scalp_uv = layout.uvs[layout.uv_faces[layout.island == 0]].reshape(-1, 2)
    assert face_uv[:, 0].min() > scalp_uv[:, 0].max(), "face island right of the scalp island"
    # every template vertex on the face border has UVs in both islands (the seam)
    face_v = set(np.unique(data.faces[layout.island == 1]).tolist())
    scalp_v = set(np.unique(data.faces[layout.island == 0]).tolist())
    assert len(face_v & scalp_v) > 50


def test_bake_roundtrip_on_template(setup):
    from headforge.craft import register as R
    from headforge.craft import uvmap

    _, template, _, duv = setup
    base = R.dense_base(template, {}, R.RegisterConfig().smooth_iterations).numpy()
    disp = _field(base)
    raw, mask = uvmap.bake(disp, duv, 256)
    assert 0.25 < mask.mean() < 0.6
    filled = uvmap.postprocess_seams(raw, mask, duv, blend=0)
    assert np.array_equal(filled[mask & ~uvmap.seam_pairs(duv, 256)[1]], raw[mask & ~uvmap.seam_pairs(duv, 256)[1]])
    back = uvmap.decode(uvmap.encode(filled))
    assert np.abs(back - filled).max() <= uvmap.QUANTUM_M
    got = uvmap.lookup(back, duv, template.n_vertices).numpy()
    err = 1000 * np.linalg.norm(got - disp, axis=1)
    free = np.union1d(template.regions["face"], template.regions["scalp"])
    assert np.median(err) < 0.2 and np.median(err[free]) < 0.1, (np.median(err), np.median(err[free]))
    # without the Voronoi fill, lookups at island borders read empty texels and fail the bound
    err_raw = 1000 * np.linalg.norm(uvmap.lookup(raw, duv, template.n_vertices).numpy() - disp, axis=1)
    assert np.percentile(err_raw, 95) > 2 * np.percentile(err, 95)


def test_seam_blend_makes_sides_agree(setup):
    from headforge.craft import uvmap

    _, template, _, duv = setup
    rng = np.random.default_rng(0)
    noisy = rng.normal(0, 0.002, (256, 256, 3))  # a "generated" map whose seam sides disagree
    mask = uvmap.texel_islands(duv, 256) >= 0
    pairs, _ = uvmap.seam_pairs(duv, 256)
    out = uvmap.postprocess_seams(noisy, mask, duv, blend=10)
    a, b = out[pairs[:, 0, 0], pairs[:, 0, 1]], out[pairs[:, 1, 0], pairs[:, 1, 1]]
    assert np.abs(a - b).max() < 1e-12
    assert (out != 0).all(), "every texel filled"
    # the blend smooths inside the band: texels next to the seam move toward the seam values
    assert np.abs(out[mask] - noisy[mask]).mean() > 1e-4


def test_map_file_roundtrip_and_bad_maps(tmp_path, setup):
    import cv2

    from headforge.craft import uvmap

    m = np.random.default_rng(1).uniform(-0.15, 0.15, (64, 64, 3))
    uvmap.write_map(tmp_path / "map.png", m, m[..., 0] > 0)
    back = uvmap.read_map(tmp_path / "map.png", 64)
    assert np.abs(back - m).max() <= uvmap.QUANTUM_M
    assert (tmp_path / "map_mask.png").exists() and not list(tmp_path.glob("*.partial*"))
    cv2.imwrite(str(tmp_path / "u8.png"), np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(HeadforgeError, match="uint16"):
        uvmap.read_map(tmp_path / "u8.png")
    with pytest.raises(HeadforgeError, match="expected 128"):
        uvmap.read_map(tmp_path / "map.png", 128)
    with pytest.raises(HeadforgeError, match="cannot read"):
        uvmap.read_map(tmp_path / "missing.png")
    # values beyond the clip range are clipped to +-20 paper units (+-167 mm)
    assert np.isclose(uvmap.decode(uvmap.encode(np.full((1, 1, 3), 1.0))).max(), uvmap.CLIP_M)
