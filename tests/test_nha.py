"""Neural Head Avatars: networks, the avatar model, training with resume, export and rendering."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh
from typer.testing import CliRunner

from headforge.avatars.nha.networks import FiLMSiren, GeometryNet, MappingNetwork, TextureNet
from headforge.errors import HeadforgeError


def test_film_siren_shapes_and_conditioning():
    torch.manual_seed(0)
    mapping, siren = MappingNetwork(3, 4, 32), FiLMSiren(5, 4, 32)
    gamma, beta = mapping(torch.randn(2, 3))
    assert gamma.shape == beta.shape == (2, 4, 32)
    assert (gamma - 1).abs().max() < 0.5  # starts near the plain SIREN
    out = siren(torch.rand(2, 7, 5) * 2 - 1, gamma, beta)
    assert out.shape == (2, 7, 32) and out.abs().max() <= 1
    g = GeometryNet(50, embed_dim=8, layers=3, width=16, max_offset=0.01)
    off = g(torch.rand(50, 3) * 2 - 1, torch.zeros(3, 3))
    assert off.shape == (3, 50, 3) and off.abs().max() <= 0.01
    assert torch.allclose(off[0], off[1])  # same condition, same offsets
    positions, cond, rows = torch.rand(50, 3) * 2 - 1, torch.randn(2, 3), torch.tensor([3, 17, 42])
    assert torch.allclose(g(positions, cond, rows), g(positions, cond)[:, rows], atol=1e-7)  # rows only
    tex = TextureNet(grid_size=16, grid_channels=4, layers=3, width=16, cond_dim=6, mouth_grid_size=8,
                     normal_channels=(8, 8, 4), head_width=8)
    mouth = torch.tensor([False, True, False, True])
    feats = torch.randn(4, 4)
    rgb = tex(torch.rand(4, 3), torch.rand(4, 2), torch.randn(4, 6), mouth, feats)
    assert rgb.shape == (4, 3) and ((rgb >= 0) & (rgb <= 1)).all()
    # the mouth condition changes mouth pixels only
    p, uv = torch.full((4, 3), 0.3), torch.full((4, 2), 0.5)
    rgb2 = tex(p, uv, torch.randn(4, 6), mouth, feats)
    rgb3 = tex(p, uv, torch.randn(4, 6), mouth, feats)
    assert torch.allclose(rgb2[~mouth], rgb3[~mouth]) and not torch.allclose(rgb2[mouth], rgb3[mouth])
    # the inner-mouth pixels read their own grid
    inner = torch.tensor([True, False, False, False])
    assert torch.equal(tex.sample_grid(uv, inner)[1:], tex.sample_grid(uv)[1:])
    assert not torch.allclose(tex.sample_grid(uv, inner)[0], tex.sample_grid(uv)[0])


def test_normal_patches_shade_the_texture_and_reach_the_geometry():
    """The second head sees the normal encoder's feature; a flat patch's feature (used for baking)
    equals the convolutional encoder's at the middle of a constant normal image."""
    torch.manual_seed(0)
    tex = TextureNet(grid_size=16, grid_channels=4, layers=3, width=16, cond_dim=6, mouth_grid_size=8,
                     normal_channels=(8, 8, 4), head_width=8)
    with torch.no_grad():
        tex.head_rgb.weight.normal_(std=0.5)  # a trained second head
    normal = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, -1.0]]), dim=-1).requires_grad_()
    image = normal[0][None, None, None].expand(1, 9, 9, 3)
    conv = tex.encode_normals(image)[0, 4, 4]
    flat = tex.encode_uniform_normals(normal)[0]
    assert torch.allclose(conv, flat, atol=1e-5)
    p, uv, cond, mouth = torch.full((1, 3), 0.3), torch.full((1, 2), 0.5), torch.zeros(1, 6), torch.zeros(1, dtype=torch.bool)
    lit = tex(p, uv, cond, mouth, tex.encode_uniform_normals(normal))
    other = tex(p, uv, cond, mouth, tex.encode_uniform_normals(torch.tensor([[0.0, 0.0, -1.0]])))
    assert (lit - other).abs().max() > 1e-3  # the colour depends on the normal
    lit.sum().backward()
    assert normal.grad.abs().max() > 0  # and a photometric loss moves the geometry


@pytest.fixture(scope="module")
def tiny_config():
    from headforge.avatars.nha.trainer import NHAConfig

    config = NHAConfig.quick()
    config.resolution = 96
    config.geometry_iters, config.texture_iters, config.joint_iters = 2, 2, 2
    config.checkpoint_every, config.val_every, config.val_frames, config.tto_steps, config.val_tto_steps = 2, 3, 2, 1, 1
    config.tex_grid, config.geo_width, config.tex_width = 32, 32, 32
    config.align_steps = 10
    return config


def test_dynamic_offsets_live_on_the_neck_only(synth_bench, tiny_config):
    from headforge.avatars.nha.trainer import build_avatar

    avatar, _ = build_avatar(synth_bench[0] / "subject_00", tiny_config)
    with torch.no_grad():
        torch.nn.init.normal_(avatar.geometry_net.head.weight, std=0.1)
        torch.nn.init.normal_(avatar.geometry_net.mapping.out.weight, std=0.05)  # a trained conditioning
        a = avatar.offsets(torch.zeros(1, 3))
        b = avatar.offsets(torch.tensor([[0.3, 0.2, 0.0]]))
    moved = (a - b).norm(dim=-1)[0]
    far = avatar.neck_fade[:, 0] == 0
    assert far.sum() > 100 and moved[far].max() < 1e-7
    assert moved[~far].max() > 1e-5
    assert avatar.head.num_vertices >= 4570  # the default template keeps the lower neck


def test_the_energies_reach_below_the_scored_neck_cut_when_the_lower_neck_is_kept(synth_bench, tiny_config):
    """With the lower neck kept, the silhouette term sees mask pixels between the scored area's
    bound (the cut's ring) and the kept neck's end; what :func:`evaluate` scores stops at the cut."""
    from headforge.avatars.nha.trainer import FrameData, _above_neck, build_avatar, composites, losses

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    res = tiny_config.resolution
    data = FrameData(dataset, "val", res)
    batch = data.batch(torch.arange(2))
    with torch.no_grad():
        verts = avatar.pose(avatar.frame_params(batch["index"]))[0]
        scored = _above_neck(avatar.neck_ring, verts, data.K, res)
        trained = _above_neck(avatar.train_ring, verts, data.K, res)
        band = trained & ~scored  # rows the energies see and the scores do not
        assert band.any() and not (scored & ~trained).any()
        flipped = dict(batch, mask=torch.where(band, 1 - batch["mask"], batch["mask"]))
        sil = [losses(avatar, b, data.K, tiny_config, "align")["silhouette"] for b in (batch, flipped)]
        assert not torch.isclose(sil[0], sil[1])
        _, _, gt, _ = composites(avatar, batch, data.K, tiny_config, matte=False)
        _, _, gt_flipped, _ = composites(avatar, flipped, data.K, tiny_config, matte=False)
        assert torch.equal(gt, gt_flipped)


def test_the_scalp_laplacian_weight_is_a_config_field(synth_bench, tiny_config):
    from dataclasses import replace

    from headforge.avatars.nha.trainer import build_avatar

    avatar, _ = build_avatar(synth_bench[0] / "subject_00", replace(tiny_config, laplacian_scalp=0.37))
    scalp = avatar.head.region("scalp")
    assert len(scalp) > 100 and torch.all(avatar.laplacian_weight[scalp] == 0.37)
    assert avatar.laplacian_weight[avatar.head.region("face")].min() == 20.0
    # the top-back of the scalp (high and behind) can be softer than the rest of it
    softer, _ = build_avatar(synth_bench[0] / "subject_00", replace(tiny_config, laplacian_scalp=0.5,
                                                                     laplacian_top_back_factor=0.2))
    w = softer.laplacian_weight[scalp]
    top_back = torch.isclose(w, torch.tensor(0.1))
    assert 0.1 * len(scalp) < top_back.sum() < 0.6 * len(scalp) and torch.all(w[~top_back] == 0.5)
    rest = softer.head.v_template[scalp]
    assert rest[top_back, 1].min() > rest[~top_back, 1].mean()  # high on the head ...
    assert rest[top_back, 2].max() <= softer.head.v_template[:, 2].mean()  # ... and behind its centre


def test_the_face_laplacian_cut_leaves_the_face_free_of_scalp_offsets(synth_bench, tiny_config):
    """Hair grown on the scalp (offsets there only) costs the stiff face nothing with
    ``laplacian_face_cut``, and as much as before without it; smooth offsets elsewhere score the
    same either way."""
    from dataclasses import replace

    from headforge.avatars.nha.trainer import build_avatar

    subject = synth_bench[0] / "subject_00"
    plain, _ = build_avatar(subject, replace(tiny_config, laplacian_face_cut=False))
    cut, _ = build_avatar(subject, replace(tiny_config, laplacian_face_cut=True))
    V = plain.head.num_vertices
    hair = torch.zeros(1, V, 3)
    hair[0, plain.head.region("scalp"), 1] = 5.0  # mm
    face_only = torch.zeros(V)
    face_only[plain.head.region("face")] = 1.0
    for avatar in (plain, cut):
        avatar.laplacian_weight.copy_(face_only)  # score the face vertices alone
    assert plain.laplacian_term(hair) > 1e-3
    assert cut.laplacian_term(hair) == 0.0
    bump = torch.randn(1, V, 3)
    for avatar in (plain, cut):
        avatar.laplacian_weight.fill_(1.0)
    inside = torch.zeros(V, dtype=torch.bool)
    inside[plain.head.region("lips")] = True  # far from the hairline: the same neighbourhoods
    bump[0, ~inside] = 0.0
    assert torch.allclose(plain.laplacian_term(bump), cut.laplacian_term(bump), rtol=1e-5, atol=1e-7)


def test_keeping_the_lower_neck_keeps_every_head_model_vertex_and_scores_above_the_same_neck_cut(synth_bench, tiny_config):
    """``remove_lower_neck=False`` (the default) trains on the whole head model, True is App. A.1's cut:
    no vertex is dropped; the ring that bounds the scored image area is the cut's, the same points
    in both templates, while the energies' area reaches down to the kept neck's open end."""
    from dataclasses import replace

    from headforge.avatars.nha.trainer import build_avatar
    from headforge.head import load_data

    subject = synth_bench[0] / "subject_00"
    cut, _ = build_avatar(subject, replace(tiny_config, remove_lower_neck=True))
    kept, _ = build_avatar(subject, replace(tiny_config, remove_lower_neck=False))
    base = load_data("open-head", None)
    lower = len(base.regions["lower_neck"])
    assert lower > 0
    assert kept.head.num_vertices == cut.head.num_vertices + lower == len(base.v_template)
    ring = lambda a: np.sort(np.round(a.head.v_template[a.neck_ring].numpy(), 6), axis=0)  # noqa: E731
    assert len(cut.neck_ring) > 0
    np.testing.assert_array_equal(ring(kept), ring(cut))
    assert kept.head.v_template[:, 1].min() < cut.head.v_template[:, 1].min() - 0.005  # the neck goes lower
    assert torch.equal(cut.train_ring, cut.neck_ring)
    kept_train_y, cut_train_y = (a.head.v_template[a.train_ring, 1].mean() for a in (kept, cut))  # +y up
    assert kept_train_y < cut_train_y - 0.005


def test_the_shell_laplacian_leaves_an_even_hair_shell_free_and_the_rest_as_before(synth_bench, tiny_config):
    """With ``laplacian_scalp_shell`` hair of even thickness along the template normal costs the
    scalp's inner vertices nothing (the vector Laplacian charges it: the normals turn); offsets
    off the scalp score as without it."""
    from dataclasses import replace

    from headforge.avatars.nha.trainer import build_avatar
    from headforge.head.topology import directed_edges

    subject = synth_bench[0] / "subject_00"
    plain, _ = build_avatar(subject, replace(tiny_config, laplacian_scalp_shell=False))
    shell, _ = build_avatar(subject, replace(tiny_config, laplacian_scalp_shell=True))
    V = plain.head.num_vertices
    scalp = torch.zeros(V, dtype=torch.bool)
    scalp[plain.head.region("scalp")] = True
    assert torch.equal(shell.shell_vertices, scalp) and not plain.shell_vertices.any()
    i, j = directed_edges(plain.head.faces, V)
    inner = scalp.clone()
    inner[i[scalp[i] & ~scalp[j]]] = False  # scalp vertices with a neighbour off the scalp
    assert inner.sum() > 20
    hair = torch.zeros(1, V, 3)
    hair[0, scalp] = 5.0 * shell.rest_normals[scalp]  # mm, along the template normal
    for avatar in (plain, shell):
        avatar.laplacian_weight.copy_(inner.float())
    assert plain.laplacian_term(hair) > 1e-3
    assert shell.laplacian_term(hair) < 1e-9
    thicker = hair.clone()
    thicker[0, scalp] *= 1.0 + (shell.rest_normals[scalp, 1:2] > 0)  # twice as thick on the upper half
    assert shell.laplacian_term(thicker) > 1e-3  # uneven thickness is still charged
    away = torch.randn(1, V, 3)
    away[0, scalp] = 0.0
    off_scalp = (~scalp).float()
    for avatar in (plain, shell):
        avatar.laplacian_weight.copy_(off_scalp)
    assert torch.allclose(plain.laplacian_term(away), shell.laplacian_term(away), rtol=1e-6)


def test_offsets_on_the_neck_rows_equal_the_full_network_evaluation(synth_bench, tiny_config):
    """The conditioned G runs on the neck-fade vertices only; values and neck-pose gradients are
    those of NHA's blend over every vertex (the pure-PyTorch reference below)."""
    from headforge.avatars.nha.trainer import build_avatar

    avatar, _ = build_avatar(synth_bench[0] / "subject_00", tiny_config)
    torch.manual_seed(0)
    with torch.no_grad():
        torch.nn.init.normal_(avatar.geometry_net.head.weight, std=0.1)
        torch.nn.init.normal_(avatar.geometry_net.mapping.out.weight, std=0.05)
    assert 0 < len(avatar.neck_rows) < avatar.head.num_vertices
    pose = torch.tensor([[0.3, 0.2, 0.0], [-0.1, 0.4, 0.1]], requires_grad=True)
    fast = avatar.offsets(pose)
    g = avatar.geometry_net
    static = g(avatar.positions, torch.zeros(1, 3))
    reference = static + avatar.neck_fade * (g(avatar.positions, pose) - static)
    assert fast.shape == reference.shape == (2, avatar.head.num_vertices, 3)
    assert torch.allclose(fast, reference, atol=1e-7)
    weights = torch.randn_like(fast)
    grad_fast, = torch.autograd.grad((fast * weights).sum(), pose)
    grad_ref, = torch.autograd.grad((reference * weights).sum(), pose)
    assert grad_ref.abs().max() > 1e-4 and torch.allclose(grad_fast, grad_ref, rtol=1e-4, atol=1e-7)


def test_joint_limited_avatar_starts_at_the_tracked_poses(synth_bench, tiny_config):
    """With NHA's tanh joint limits the frame poses are raw parameters; they start where the
    limited poses equal the tracked ones, so a fresh avatar (zero offsets) is posed exactly
    like the tracked head model, and driving sequences are converted the same way."""
    from safetensors.torch import load_file

    from headforge.avatars.nha.trainer import build_avatar
    from headforge.head.model import POSE_ARGS

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    assert avatar.head.joint_limits
    tracked = load_file(str(dataset / "tracking.safetensors"))
    rows = torch.arange(3)
    with torch.no_grad():
        torch.nn.init.zeros_(avatar.geometry_net.head.weight)
        torch.nn.init.zeros_(avatar.geometry_net.head.bias)
        params = avatar.frame_params(rows)
        assert not torch.allclose(params["neck_pose"], tracked["neck_pose"][rows].float())  # raw, not tracked
        verts, _, offsets = avatar.pose(params)
        assert offsets.abs().max() == 0
        avatar.head.joint_limits = False  # the same model without limits, fed the tracked poses
        ref = avatar.head(shape=avatar.shape.expand(3, -1), expression=tracked["expression"][rows].float(),
                          **{k: tracked[k][rows].float() for k in POSE_ARGS}).vertices
        avatar.head.joint_limits = True
    ref = ref * torch.tensor([1.0, -1.0, -1.0]) + tracked["translation"][rows].float()[:, None]
    torch.testing.assert_close(verts, ref, atol=2e-6, rtol=1e-4)
    driven = avatar.params_from_tracking(tracked)
    assert all(torch.allclose(driven[k], avatar.frames[k].detach()) for k in driven)


def test_eyelid_term_measures_the_eye_opening():
    from headforge.avatars.nha.model import EYELID_PAIRS
    from headforge.avatars.nha.trainer import eyelid_term

    torch.manual_seed(0)
    detected = torch.rand(2, 478, 2) * 200
    assert eyelid_term(detected.clone(), detected) == 0
    assert eyelid_term(detected + torch.tensor([5.0, -3.0]), detected) < 1e-4  # a shift keeps the opening
    closed = detected.clone()
    for up, lo in EYELID_PAIRS:
        closed[:, up] = closed[:, lo]  # a blink in the detections
    assert eyelid_term(detected, closed) > 1.0
    missing = detected.clone()
    missing[0, EYELID_PAIRS[0][0]] = float("nan")  # an undetected landmark does not count
    assert torch.isfinite(eyelid_term(detected, missing))


def test_normal_patches_on_the_bounding_box_equal_the_whole_image(synth_bench, tiny_config):
    from headforge.avatars.nha.trainer import FrameData, _cameras, build_avatar
    from headforge.head.topology import vertex_normals
    from headforge.render import mesh

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    data = FrameData(dataset, "val", tiny_config.resolution)
    cams = _cameras(data.K, 2, tiny_config.resolution)
    verts = avatar.pose(avatar.frame_params(data.index[:2]))[0]
    faces = avatar.head.faces
    frags = mesh.rasterize(cams, verts, faces)
    bary = mesh.barycentrics(frags, cams, verts, faces)
    hit = frags.face_id >= 0
    assert 0 < hit.float().mean() < 0.7  # the crop is smaller than the image
    cropped, normals = avatar._normal_patches(verts, frags, bary, hit)
    image = mesh.interpolate(vertex_normals(verts, faces), frags, faces, bary)
    whole = avatar.texture_net.encode_normals(image)[hit]
    assert torch.allclose(cropped, whole, atol=1e-6)
    assert torch.equal(normals, image[hit])


def test_albedo_tv_charges_a_smooth_ramp_in_full_and_a_step_only_at_its_edge():
    from headforge.avatars.nha.trainer import albedo_tv

    inside = torch.zeros(1, 8, 8, dtype=torch.bool)
    inside[:, 1:7, 1:7] = True
    ramp = torch.linspace(0, 0.5, 8)[None, None, :, None].expand(1, 8, 8, 3).clone()
    step = torch.zeros(1, 8, 8, 3)
    step[:, :, 4:] = 0.5  # the same rise, all at once
    # 30 horizontal + 30 vertical neighbour pairs inside; the ramp rises 0.5/7 on each horizontal one
    assert albedo_tv(ramp, inside).item() == pytest.approx(30 * 0.5 / 7 / 60, rel=1e-5)
    assert albedo_tv(step, inside).item() == pytest.approx(6 * 0.5 / 60, rel=1e-5)
    outside = ramp.clone()
    outside[:, 0] = 9.0  # pixels outside ``inside`` cost nothing
    assert albedo_tv(outside, inside).item() == pytest.approx(albedo_tv(ramp, inside).item())


def test_a_shading_avatar_lights_its_albedo_at_the_rendered_normals(synth_bench, tiny_config):
    """With ``shading`` the colour is T's albedo times the SH irradiance at the pixel's normal:
    under a uniform environment the render is the albedo scaled, and a directional light makes
    the colour depend on (and its gradient reach) the vertices through the normals."""
    from dataclasses import replace

    from headforge.avatars.nha.export import bake_texture
    from headforge.avatars.nha.trainer import FrameData, _cameras, build_avatar, losses
    from headforge.render.shading import constant_sh

    dataset = synth_bench[0] / "subject_00"
    config = replace(tiny_config, shading=True)
    avatar, _ = build_avatar(dataset, config)
    plain, _ = build_avatar(dataset, tiny_config)
    assert plain.sh is None and "sh" not in plain.state_dict()
    data = FrameData(dataset, "val", config.resolution)
    cams = _cameras(data.K, 1, config.resolution)
    params = avatar.frame_params(data.index[:1])
    with torch.no_grad():
        avatar.sh.copy_(constant_sh(0.5))
        r = avatar.render(params, cams, background=1.0, matte=False)
    inner = torch.nn.functional.max_pool2d((~r.fragments.mask).float()[:, None], 3, 1, 1)[:, 0] == 0
    assert inner.sum() > 100
    assert torch.allclose(r.rgb[inner], 0.5 * r.albedo[inner], atol=1e-5)
    with torch.no_grad():
        avatar.sh.zero_()
        avatar.sh[0] = 1.0
        avatar.sh[2] = 0.8  # light along camera y: varies with the normal
        lit = avatar.render(params, cams, background=1.0, matte=False)
    ratio = (lit.rgb[inner] / lit.albedo[inner].clamp(min=1e-3))[:, 0]
    assert ratio.std() > 0.05  # the irradiance changes across the head
    batch = data.batch(torch.arange(1))
    out = losses(avatar, batch, data.K, config, "joint")
    assert out["albedo_tv"] > 0
    out["rgb"].backward()
    assert avatar.sh.grad.abs().sum() > 0
    assert avatar.geometry_net.embedding.grad.abs().sum() > 0  # through the positions and the normals
    texture = bake_texture(avatar, size=32)
    assert texture.shape == (32, 32, 3) and np.isfinite(texture).all()


def test_contour_term_leaves_out_rims_inside_the_silhouette(synth_bench, tiny_config):
    """Against the avatar's own silhouette the outline term is about a pixel: the occluding rims
    inside it (the nose's flanks, a cheek, the far side of the head) are left out rather than
    pulled toward the outline, which they are far from."""
    from headforge.avatars.nha.trainer import FrameData, _above_neck, _cameras, build_avatar, contour_term, outer_band
    from headforge.render import mesh

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    res = tiny_config.resolution
    data = FrameData(dataset, "val", res)
    with torch.no_grad():
        verts = avatar.pose(avatar.frame_params(data.index[:2]))[0]
        covered = mesh.rasterize(_cameras(data.K, 2, res), verts, avatar.head.faces).face_id >= 0
    band = outer_band(covered, width=2)
    assert band[~covered].all() and not band[covered].all() and band[covered].any()
    area = _above_neck(avatar.neck_ring, verts, data.K, res)
    own = covered.float() * area
    kept = contour_term(avatar, verts, own, area, data.K, res, covered) * res  # pixels
    everything = contour_term(avatar, verts, own, area, data.K, res) * res
    assert kept < 3.0
    assert everything > 2 * kept


def test_face_oval_masks_fill_the_detected_loop():
    from headforge.avatars.nha.trainer import face_oval_masks
    from headforge.head.landmarks import FACE_OVAL_LOOP

    angles = torch.linspace(0, 2 * np.pi, len(FACE_OVAL_LOOP) + 1)[:-1]
    landmarks = torch.full((3, 478, 2), 32.0)
    landmarks[:, list(FACE_OVAL_LOOP)] = torch.stack([32 + 20 * angles.sin(), 32 - 20 * angles.cos()], -1)
    landmarks[1, FACE_OVAL_LOOP[5]] = float("nan")  # a missing loop point: no region for that frame
    masks, known = face_oval_masks(landmarks, 64)
    assert known.tolist() == [True, False, True]
    assert masks[0, 32, 32] == 255 and masks[0, 2, 2] == 0 and masks[1].max() == 0
    area = masks[0].float().sum() / 255
    polygon = 0.5 * len(FACE_OVAL_LOOP) * 20**2 * np.sin(2 * np.pi / len(FACE_OVAL_LOOP))
    assert abs(area - polygon) < 0.02 * polygon  # the coverage is the polygon's, edges partial
    assert ((masks[0] > 0) & (masks[0] < 255)).any()
    _, known68 = face_oval_masks(torch.zeros(2, 68, 2), 64)  # iBUG landmarks: no oval loop
    assert not known68.any()


def test_semantic_term_compares_the_rendered_face_oval_with_the_detected_one(synth_bench, tiny_config):
    """The avatar's face-oval region (template vertices inside the landmark loop) renders where
    its own projected oval landmarks outline it, and the semantic term moves the geometry."""
    from headforge.avatars.nha.trainer import FrameData, _cameras, build_avatar, face_oval_masks, losses

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    head = avatar.head
    oval = avatar.face_oval[:, 0].bool()
    for name in ("scalp", "ears", "neck"):
        if name in head.region_names:
            assert not oval[head.region(name)].any()
    assert oval[head.region("face")].float().mean() > 0.7
    res = tiny_config.resolution
    data = FrameData(dataset, "val", res)
    cams = _cameras(data.K, 2, res)
    params = avatar.frame_params(data.index[:2])
    with torch.no_grad():
        r = avatar.render(params, cams, texture=False, face_region=True)
    own = face_oval_masks(r.landmarks[..., :2] / r.landmarks[..., 2:] * data.K[0, 0] + data.K[:2, 2], res)[0] > 127
    rendered = r.face_region > 0.5
    assert (own & rendered).sum() / (own | rendered).sum() > 0.9
    batch = data.batch(torch.arange(2))
    terms = losses(avatar, batch, data.K, tiny_config, "geometry")
    assert 0 < terms["semantic"] < 0.2 * tiny_config.w_semantic
    terms["semantic"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in avatar.geometry_net.parameters())


def test_face_region_matches_full_image_barycentric_interpolation(synth_bench, tiny_config):
    """The face region differentiates only the triangles straddling the oval's border; values
    and vertex gradients equal interpolating with differentiable barycentrics everywhere."""
    from headforge.avatars.nha.trainer import FrameData, _cameras, build_avatar
    from headforge.render import mesh

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    data = FrameData(dataset, "val", tiny_config.resolution)
    cams = _cameras(data.K, 2, tiny_config.resolution)
    with torch.no_grad():
        verts = avatar.pose(avatar.frame_params(data.index[:2]))[0].double()
    faces = avatar.head.faces
    frags = mesh.rasterize(cams, verts, faces)
    weight = torch.rand(frags.face_id.shape, dtype=torch.float64)
    grads = []
    for fast in (True, False):
        v = verts.clone().requires_grad_(True)
        if fast:
            region = avatar._face_region(frags, cams, v)
        else:
            region = mesh.interpolate(avatar.face_oval.double(), frags, faces, mesh.barycentrics(frags, cams, v, faces))
        (region[..., 0] * weight).sum().backward()
        grads.append((region.detach(), v.grad))
    assert ((grads[0][0] > 0) & (grads[0][0] < 1)).any()  # there is a border with fractional values
    torch.testing.assert_close(grads[0][0], grads[1][0], atol=1e-9, rtol=0)
    assert grads[0][1].abs().sum() > 0
    torch.testing.assert_close(grads[0][1], grads[1][1], atol=1e-7, rtol=1e-6)


def test_align_frames_recovers_a_shifted_frame_and_touches_no_other(synth_bench, tiny_config):
    """Per-frame fitting with frozen networks pulls a frame moved 15 mm sideways back toward its
    tracked pose (which fits the GT mask and landmarks of the synthetic render) and leaves the
    frames outside ``rows`` and the networks untouched."""
    from dataclasses import replace

    from headforge.avatars.nha.trainer import FrameData, _subset, align_frames, build_avatar, losses, validate

    config = replace(tiny_config, resolution=128)
    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, config)
    data = FrameData(dataset, "val", config.resolution)
    rows = torch.tensor([0, 1])
    idx = data.index[rows]
    tracked = avatar.frames["translation"].detach().clone()

    def projected():  # (2, V, 2) pixels
        with torch.no_grad():
            v = avatar.pose(avatar.frame_params(idx))[0]
        return v[..., :2] / v[..., 2:] * data.K[0, 0]

    target = projected()
    with torch.no_grad():
        avatar.frames["translation"][idx, 0] += 0.015
    weights = {k: v.detach().clone() for k, v in avatar.state_dict().items() if not k.startswith("frames")}

    def data_terms():
        with torch.no_grad():
            return sum(losses(avatar, data.batch(rows), data.K, config, "align").values()).item()

    before, moved = data_terms(), (projected() - target).norm(dim=-1).mean()
    align_frames(avatar, data, data.K, config, steps=25, rows=rows)
    assert data_terms() < 0.7 * before
    assert (projected() - target).norm(dim=-1).mean() < 0.5 * moved  # the image-space shift mostly undone
    others = torch.ones(len(tracked), dtype=torch.bool)
    others[idx] = False
    assert torch.equal(avatar.frames["translation"].detach()[others], tracked[others])
    assert not torch.equal(avatar.frames["translation"].detach()[idx], tracked[idx])
    for k, v in avatar.state_dict().items():
        if not k.startswith("frames"):
            assert torch.equal(v, weights[k]), k
    assert all(p.requires_grad for p in avatar.geometry_net.parameters())
    # validation during training fits its frames but gives them back their parameters
    frames = {k: v.detach().clone() for k, v in avatar.frames.items()}
    scores = validate(avatar, _subset(data, torch.tensor([2, 3])), data.K, config)
    assert 5 < scores["psnr"] < 60
    assert all(torch.equal(avatar.frames[k].detach(), v) for k, v in frames.items())


def test_fit_resumes_exports_and_renders(synth_bench, tiny_config, tmp_path, interrupt_after):
    from headforge.avatars.nha.trainer import fit, load_run
    from headforge.cli import app

    dataset = synth_bench[0] / "subject_00"
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        fit(dataset, run, tiny_config, log=lambda m: None, progress=interrupt_after(3))
    assert json.loads((run / "state.json").read_text())["iteration"] == 2
    # a run written before a config field existed resumes with that field's default
    written = json.loads((run / "config.json").read_text())
    del written["config"]["laplacian_scalp"]
    (run / "config.json").write_text(json.dumps(written))
    with pytest.raises(HeadforgeError, match="other settings"):  # ... not with another value of it
        fit(dataset, run, type(tiny_config)(**{**tiny_config.__dict__, "laplacian_scalp": 0.5}), log=lambda m: None)
    logs = []
    metrics = fit(dataset, run, tiny_config, log=logs.append)
    assert any("resuming" in m for m in logs)
    assert json.loads((run / "state.json").read_text())["iteration"] == 6
    assert metrics["val_frames"] >= 1 and 5 < metrics["val_psnr"] < 60 and 0 < metrics["val_ssim"] <= 1
    for name in ("progress.png", "metrics.json", "losses.csv", "checkpoint.safetensors", "geometry.safetensors"):
        assert (run / name).is_file(), name
    assert list((run / "val").glob("*.png"))
    # the exported geometry is what headforge eval reads
    from headforge.metrics.benchmark import evaluate_geometry

    result = evaluate_geometry(run, dataset, samples=500)
    assert result["frames"] >= 1 and np.isfinite(result["mean"]["hausdorff_full_mm"])
    # another config in the same folder is refused
    other = type(tiny_config)(**{**tiny_config.__dict__, "seed": 1})
    with pytest.raises(HeadforgeError, match="other settings"):
        fit(dataset, run, other, log=lambda m: None)
    # the soft matte is fitted after training and scored against the hard edge
    assert 0 <= metrics["matte_sigma_px"] <= 4 and 5 < metrics["val_psnr_hard_edge"] < 60
    avatar, _, _ = load_run(run)
    assert float(avatar.matte_sigma) == metrics["matte_sigma_px"]
    runner = CliRunner()
    res = runner.invoke(app, ["export", str(run), "-o", str(tmp_path / "obj"), "--frames", "0-1", "--texture-size", "64"])
    assert res.exit_code == 0, res.output
    m = trimesh.load(tmp_path / "obj" / "avatar.obj", process=False)
    assert len(m.faces) == len(avatar.head.faces) and (tmp_path / "obj" / "texture.png").is_file()
    assert (tmp_path / "obj" / "frames" / "00001.obj").is_file()
    for fmt in ("ply", "glb"):
        res = runner.invoke(app, ["export", str(run), "-o", str(tmp_path / fmt), "--format", fmt, "--texture-size", "32"])
        assert res.exit_code == 0, res.output
        assert (tmp_path / fmt / f"avatar.{fmt}").stat().st_size > 1000
    res = runner.invoke(app, ["render", "avatar", str(run), "-o", str(tmp_path / "re.mp4"), "--driving", str(dataset),
                              "--orbit", "--max-frames", "3"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "re.mp4").stat().st_size > 1000


def test_nha_bad_inputs(tmp_path, tiny_config):
    from headforge.avatars.nha.trainer import fit, load_run
    from headforge.cli import app

    with pytest.raises(HeadforgeError, match="not a headforge run"):
        load_run(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"format": "headforge-run", "method": "point"}))
    with pytest.raises(HeadforgeError, match="not an NHA run"):
        load_run(tmp_path)
    newer = {"format": "headforge-run", "method": "nha", "dataset": str(tmp_path), "config": {"hair_cards": 3}}
    (tmp_path / "config.json").write_text(json.dumps(newer))
    with pytest.raises(HeadforgeError, match="another headforge version .*hair_cards"):
        load_run(tmp_path)
    from headforge.avatars.nha.trainer import NHAConfig

    # A run written before laplacian_face_cut existed trained without it, whatever today's default.
    assert NHAConfig().laplacian_face_cut is True
    assert NHAConfig.from_saved({"seed": 3}, tmp_path).laplacian_face_cut is False
    assert NHAConfig.from_saved({"laplacian_face_cut": True}, tmp_path).laplacian_face_cut is True
    # ...and one written before remove_lower_neck existed trained on the cut template.
    assert NHAConfig().remove_lower_neck is False
    assert NHAConfig.from_saved({"seed": 3}, tmp_path).remove_lower_neck is True
    with pytest.raises(HeadforgeError, match="not a headforge dataset"):
        fit(tmp_path / "nothing", tmp_path / "run", tiny_config, log=lambda m: None)
    res = CliRunner().invoke(app, ["fit", "nha", str(tmp_path), "-o", str(tmp_path / "r"), "--preset", "fast"])
    assert res.exit_code != 0 and "--preset" in str(res.exception)
    for bad, message in (("tex_grids=256", "NHAConfig field"), ("tex_grid=big", "not a int"), ("subdivide=maybe", "not a bool")):
        res = CliRunner().invoke(app, ["fit", "nha", str(tmp_path), "-o", str(tmp_path / "r"), "--set", bad])
        assert res.exit_code != 0 and message in str(res.exception)
    assert not (tmp_path / "r").exists()


def test_learning_rates_decay_along_a_half_cosine_at_the_end():
    from headforge.avatars.nha.trainer import NHAConfig, lr_factor

    config = NHAConfig.quick()  # 2000 iterations, decay from 1400
    factors = [lr_factor(it, config) for it in range(config.total_iters + 1)]
    assert factors[:1401] == [1.0] * 1401
    assert all(a >= b for a, b in zip(factors, factors[1:])) and factors[-1] == pytest.approx(config.lr_final)
    assert factors[1700] == pytest.approx((1 + config.lr_final) / 2)  # half way down
    config.override("lr_final=1.0")
    assert {lr_factor(it, config) for it in range(config.total_iters + 1)} == {1.0}


def test_config_overrides_parse_as_the_field_types():
    from headforge.avatars.nha.trainer import NHAConfig

    config = NHAConfig.quick()
    for assignment in ("tex_grid=256", "lr_grid=0.02", "subdivide=true", "normal_channels=32,32,16"):
        config.override(assignment)
    assert (config.tex_grid, config.lr_grid, config.subdivide, config.normal_channels) == (256, 0.02, True, (32, 32, 16))
    for negative in ("w_rgb=-1", "laplacian_top_back_factor=-0.2"):  # a negative weight would reward the error
        with pytest.raises(HeadforgeError, match=">= 0"):
            config.override(negative)
    assert config.w_rgb == NHAConfig.quick().w_rgb  # a refused value leaves the field as it was


def test_device_choice_is_checked(tmp_path, monkeypatch):
    from headforge.cli import app
    from headforge.devices import resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu") and resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(HeadforgeError, match="sees no CUDA GPU"):
        resolve_device("cuda")
    for bad in ("gpu", "mps"):
        with pytest.raises(HeadforgeError, match="auto, cpu or cuda"):
            resolve_device(bad)
    res = CliRunner().invoke(app, ["fit", "nha", str(tmp_path), "-o", str(tmp_path / "r"), "--device", "cuda"])
    assert res.exit_code != 0 and "no CUDA GPU" in str(res.exception)
    assert not (tmp_path / "r").exists()


def record_chunks(monkeypatch, trainer, steps_field: str, die_at: int) -> tuple[list, dict]:
    """Patch ``trainer.align_frames`` to record the ``rows`` of each call made with
    ``cfg.<steps_field>`` steps and a row chunk (the training-frame alignment: align_steps; the
    held-out frames' test-time fitting: tto_steps) and to raise KeyboardInterrupt (a kill) on
    the ``die["at"]``-th such call. Returns (chunks, die)."""
    real = trainer.align_frames
    chunks, die = [], {"at": die_at}

    def recording(avatar, data, K, cfg, steps, photometric_steps=0, rows=None):
        if rows is not None and steps == getattr(cfg, steps_field):
            chunks.append(rows.tolist())
            if len(chunks) == die["at"]:
                raise KeyboardInterrupt
        return real(avatar, data, K, cfg, steps, photometric_steps, rows)

    monkeypatch.setattr(trainer, "align_frames", recording)
    return chunks, die


def test_a_run_killed_during_the_alignment_resumes_there(synth_bench, tiny_config, tmp_path, monkeypatch):
    """Alignment checkpoints every ALIGN_CHECKPOINT_FRAMES frames: a kill in the middle of it
    loses at most that many frames' alignment, and the resumed run aligns only the rest."""
    from headforge.avatars.nha import trainer

    dataset = synth_bench[0] / "subject_00"
    config = type(tiny_config)(**{**tiny_config.__dict__, "align_steps": 1, "tto_steps": 2})
    monkeypatch.setattr(trainer, "ALIGN_CHECKPOINT_FRAMES", 4)
    chunks, die = record_chunks(monkeypatch, trainer, "align_steps", die_at=2)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        trainer.fit(dataset, run, config, log=lambda m: None)
    state = json.loads((run / "state.json").read_text())
    assert (state["iteration"], state["aligned"]) == (config.geometry_iters, 4)
    chunks.clear()
    die["at"] = -1
    logs = []
    trainer.fit(dataset, run, config, log=logs.append)
    n_train = len(trainer.FrameData(dataset, "train", config.resolution))
    assert chunks[0] == [4, 5, 6, 7] and chunks[-1][-1] == n_train - 1 and len(chunks) == -(-(n_train - 4) // 4)
    assert any(f"aligning training frames 4..{n_train}" in m for m in logs)
    assert json.loads((run / "state.json").read_text())["aligned"] == n_train


def test_a_run_killed_during_the_test_time_fitting_resumes_there(synth_bench, tiny_config, tmp_path, monkeypatch):
    """The held-out frames' test-time fitting checkpoints every TTO_CHECKPOINT_FRAMES frames: a
    kill in the middle of it keeps the frames fitted so far, and the resumed run neither trains
    nor fits the matte again, fits only the remaining frames and then writes the metrics."""
    from headforge.avatars.nha import trainer

    dataset = synth_bench[0] / "subject_00"
    config = type(tiny_config)(**{**tiny_config.__dict__, "align_steps": 1, "tto_steps": 2})
    monkeypatch.setattr(trainer, "TTO_CHECKPOINT_FRAMES", 4)
    chunks, die = record_chunks(monkeypatch, trainer, "tto_steps", die_at=2)
    real_matte, mattes = trainer.fit_matte, []

    def counting_matte(*args, **kwargs):
        mattes.append(1)
        return real_matte(*args, **kwargs)

    monkeypatch.setattr(trainer, "fit_matte", counting_matte)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        trainer.fit(dataset, run, config, log=lambda m: None)
    state = json.loads((run / "state.json").read_text())
    assert (state["iteration"], state["tested"]) == (config.total_iters, 4)
    assert not (run / "metrics.json").exists() and len(mattes) == 1
    killed = trainer.load_run(run)[0]
    fitted, sigma = killed.frames["expression"].detach().clone(), float(killed.matte_sigma)
    chunks.clear()
    die["at"] = -1
    losses_before = (run / "losses.csv").read_text()
    metrics = trainer.fit(dataset, run, config, log=lambda m: None)
    val = trainer.FrameData(dataset, "val", config.resolution)
    n_val = len(val)
    assert n_val > 4 and [r for c in chunks for r in c] == list(range(4, n_val))  # only the rest, once
    assert len(mattes) == 1 and (run / "losses.csv").read_text() == losses_before  # no training, no new matte
    assert json.loads((run / "metrics.json").read_text())["val_psnr"] == metrics["val_psnr"]
    assert metrics["matte_sigma_px"] == pytest.approx(sigma)
    resumed = trainer.load_run(run)[0].frames["expression"].detach()
    first = val.index[:4]  # the frames fitted before the kill keep their parameters
    assert torch.equal(resumed[first], fitted[first])


def test_soft_matte_changes_only_the_edge_and_old_runs_load_without_it(synth_bench, tiny_config, tmp_path):
    from safetensors.torch import load_file, save_file

    from headforge.avatars.nha.trainer import FrameData, _cameras, _load_weights, build_avatar

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    data = FrameData(dataset, "train", tiny_config.resolution)
    params, cams = avatar.frame_params(data.index[:1]), _cameras(data.K, 1, tiny_config.resolution)
    with torch.no_grad():
        hard = avatar.render(params, cams)
        avatar.matte_sigma.fill_(1.5)
        soft = avatar.render(params, cams)
        assert torch.equal(avatar.render(params, cams, matte=False).rgb, hard.rgb)
    changed = (soft.rgb - hard.rgb).abs().amax(-1) > 1e-4
    edge = (hard.coverage > 0) & (hard.coverage < 1)
    near_edge = torch.nn.functional.max_pool2d(edge.float()[:, None], 2 * 5 + 1, 1, 5)[:, 0] > 0  # 3 sigma + 1 px
    assert changed.any() and not (changed & ~near_edge).any()
    # a checkpoint written before the matte existed loads with the hard edge
    path = tmp_path / "old.safetensors"
    state = {k: v for k, v in avatar.state_dict().items() if not k.startswith("matte_")}
    save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    _load_weights(avatar, path)
    assert float(avatar.matte_sigma) == 0
    assert set(load_file(str(path))) == set(state)


def test_in_training_validation_fits_for_val_tto_steps_and_restores_the_frames(monkeypatch):
    from types import SimpleNamespace

    from headforge.avatars.nha import trainer

    config = trainer.NHAConfig.quick()
    assert config.val_tto_steps < config.tto_steps
    calls = []

    def fake_align(avatar, data, K, cfg, steps, photometric_steps=0, rows=None):
        calls.append(steps)
        avatar.frames["expression"][data.index] += 1.0  # the fitting moves the held-out frames

    monkeypatch.setattr(trainer, "align_frames", fake_align)
    monkeypatch.setattr(trainer, "evaluate", lambda avatar, data, K, cfg, out_dir=None: {"psnr": 0.0})
    avatar = SimpleNamespace(frames={"expression": torch.zeros(5, 3)})
    data = SimpleNamespace(index=torch.tensor([1, 3]))
    trainer.validate(avatar, data, None, config)
    trainer.test_time_optimise(avatar, data, None, config)
    assert calls == [config.val_tto_steps, config.tto_steps]
    assert avatar.frames["expression"][[0, 2, 4]].abs().sum() == 0
    assert avatar.frames["expression"][[1, 3]].eq(1.0).all()  # validate restored its fit; the final fit stays
