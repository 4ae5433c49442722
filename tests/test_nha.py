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
from headforge.render.camera import Cameras


def build_avatar(dataset, config):
    """(NHA avatar of a dataset, its assets)."""
    from headforge.avatars.nha.method import build_avatar as build
    from headforge.avatars.run import RunAssets

    assets = RunAssets.from_dataset(dataset)
    return build(assets, config), assets


def FrameData(dataset, split, resolution, supervision="predicted"):
    from headforge.avatars.frames import FrameData as Frames
    from headforge.avatars.run import RunAssets
    from headforge.metrics.protocol import TrackedHead

    assets = RunAssets.from_dataset(dataset)
    return Frames(dataset, split, resolution, TrackedHead(assets.head_data(), assets.tracking["shape"]),
                  supervision=supervision)


def _cameras(K, B, res):
    return Cameras.at_origin(K, B, res)


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
    from headforge.avatars.nha.config import NHAConfig

    config = NHAConfig.quick()
    config.resolution = 96
    config.geometry_iters, config.texture_iters, config.joint_iters = 2, 2, 2
    config.checkpoint_every, config.val_every, config.val_frames, config.tto_steps, config.val_tto_steps = 2, 3, 2, 1, 1
    config.tex_grid, config.geo_width, config.tex_width = 32, 32, 32
    config.align_steps = 10
    return config


def test_dynamic_offsets_live_on_the_neck_only(synth_bench, tiny_config):
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


def test_the_energies_reach_below_the_neck_cut_and_the_scores_follow_the_tracked_head(synth_bench, tiny_config):
    """With the lower neck kept, the silhouette term sees mask pixels below NHA's cut; what the
    protocol scores is the tracked head model's region, which the avatar's own template does not
    change (the same pixels with and without the lower neck)."""
    from dataclasses import replace

    from headforge.avatars.nha.method import _above_neck, losses

    dataset = synth_bench[0] / "subject_00"
    avatar, _ = build_avatar(dataset, tiny_config)
    cut, _ = build_avatar(dataset, replace(tiny_config, remove_lower_neck=True))
    res = tiny_config.resolution
    data = FrameData(dataset, "val", res)
    batch = data.batch(torch.arange(2))
    with torch.no_grad():
        verts = avatar.pose(avatar.frame_params(batch["index"]))[0]
        cut_verts = cut.pose(cut.frame_params(batch["index"]))[0]
        trained = _above_neck(avatar.train_ring, verts, data.K, res)
        cut_rows = _above_neck(cut.train_ring, cut_verts, data.K, res)
        band = trained & ~cut_rows  # rows the kept neck's energies see and the cut's do not
        assert band.any() and not (cut_rows & ~trained).any()
        flipped = dict(batch, mask=torch.where(band, 1 - batch["mask"], batch["mask"]))
        sil = [losses(avatar, b, data.K, tiny_config, "align")["silhouette"] for b in (batch, flipped)]
        assert not torch.isclose(sil[0], sil[1])
    region = batch["region"]  # the protocol's head region: from the tracked head model, per frame
    assert region.any(-1).any(-1).all() and (~region).any()
    assert (region & (batch["mask"] > 0.5)).sum() > 0.8 * ((batch["mask"] > 0.5) & trained).sum() * 0.5
    # the energies also see the protocol's region where it reaches below the rows (a looking-down
    # chin): pixels below the rows count once the region holds them, and not before
    below = ~trained & (torch.rand(trained.shape, generator=torch.Generator().manual_seed(0)) < 0.3)
    flipped = dict(batch, mask=torch.where(below, 1 - batch["mask"], batch["mask"]))
    for reach, counts in ((batch["region"] & trained, False), (batch["region"] | below, True)):
        sil = [losses(avatar, dict(b, region=reach), data.K, tiny_config, "align")["silhouette"]
               for b in (batch, flipped)]
        assert torch.isclose(sil[0], sil[1]) != counts


def test_the_scalp_laplacian_weight_is_a_config_field(synth_bench, tiny_config):
    from dataclasses import replace

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


def test_keeping_the_lower_neck_keeps_every_head_model_vertex_and_trains_down_to_its_end(synth_bench, tiny_config):
    """``remove_lower_neck=False`` (the default) trains on the whole head model, True is App. A.1's cut:
    no vertex is dropped; NHA's cut ring is the same points in both templates, while the
    energies' area reaches down to the kept neck's open end."""
    from dataclasses import replace

    from headforge.head import load_data
    from headforge.head.topology import neck_cut_ring

    subject = synth_bench[0] / "subject_00"
    cut, _ = build_avatar(subject, replace(tiny_config, remove_lower_neck=True))
    kept, _ = build_avatar(subject, replace(tiny_config, remove_lower_neck=False))
    base = load_data("open-head", None)
    lower = len(base.regions["lower_neck"])
    assert lower > 0
    assert kept.head.num_vertices == cut.head.num_vertices + lower == len(base.v_template)
    assert kept.head.v_template[:, 1].min() < cut.head.v_template[:, 1].min() - 0.005  # the neck goes lower
    ring = np.sort(np.round(np.asarray(base.v_template, np.float32)[neck_cut_ring(base)], 6), axis=0)
    cut_ring = np.sort(np.round(cut.head.v_template[cut.train_ring].numpy(), 6), axis=0)
    np.testing.assert_array_equal(ring, cut_ring)  # the cut template's open end is NHA's cut
    kept_train_y, cut_train_y = (a.head.v_template[a.train_ring, 1].mean() for a in (kept, cut))  # +y up
    assert kept_train_y < cut_train_y - 0.005


def test_the_shell_laplacian_leaves_an_even_hair_shell_free_and_the_rest_as_before(synth_bench, tiny_config):
    """With ``laplacian_scalp_shell`` hair of even thickness along the template normal costs the
    scalp's inner vertices nothing (the vector Laplacian charges it: the normals turn); offsets
    off the scalp score as without it."""
    from dataclasses import replace

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
    from headforge.avatars.supervision import eyelid_term
    from headforge.head.landmarks import EYELID_PAIRS

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
    from headforge.avatars.nha.method import albedo_tv

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
    from headforge.avatars.nha.method import losses
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
    from headforge.avatars.nha.method import _above_neck, contour_term, outer_band
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
    from headforge.head import load_data
    from headforge.head.topology import neck_cut_ring

    cut = torch.as_tensor(neck_cut_ring(load_data("open-head")))  # the quick template is open-head's own
    area = _above_neck(cut, verts, data.K, res)
    own = covered.float() * area
    kept = contour_term(avatar, verts, own, area, data.K, res, covered) * res  # pixels
    everything = contour_term(avatar, verts, own, area, data.K, res) * res
    assert kept < 3.0
    assert everything > 2 * kept


def test_face_oval_masks_fill_the_detected_loop():
    from headforge.avatars.frames import face_oval_masks
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
    from headforge.avatars.frames import face_oval_masks
    from headforge.avatars.nha.method import losses

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

    from headforge.avatars.engine import fit_frames, validate
    from headforge.avatars.nha.method import NHAMethod, losses

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
    fit_frames(NHAMethod(), avatar, data, config, steps=25, rows=rows)
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
    scores = validate(NHAMethod(), avatar, data.subset(torch.tensor([2, 3])), config)
    assert 5 < scores["psnr"] < 60
    assert all(torch.equal(avatar.frames[k].detach(), v) for k, v in frames.items())


def test_fit_resumes_exports_and_renders(synth_bench, tiny_config, tmp_path, interrupt_after):
    from headforge.avatars.engine import fit as engine_fit
    from headforge.avatars.run import load_run
    from headforge.cli import app

    def fit(*args, **kwargs):
        return engine_fit("nha", *args, **kwargs)

    dataset = synth_bench[0] / "subject_00"
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        fit(dataset, run, tiny_config, log=lambda m: None, progress=interrupt_after(3))
    assert json.loads((run / "state.json").read_text())["iteration"] == 2
    # a run written before a config field existed resumes with that field's default
    written = json.loads((run / "run.json").read_text())
    del written["config"]["laplacian_scalp"]
    (run / "run.json").write_text(json.dumps(written))
    with pytest.raises(HeadforgeError, match="other settings"):  # ... not with another value of it
        fit(dataset, run, type(tiny_config)(**{**tiny_config.__dict__, "laplacian_scalp": 0.5}), log=lambda m: None)
    logs = []
    metrics = fit(dataset, run, tiny_config, log=logs.append)
    assert any("resuming" in m for m in logs)
    assert json.loads((run / "state.json").read_text())["iteration"] == 6
    assert metrics["val_frames"] >= 1 and 5 < metrics["val_psnr"] < 60 and 0 < metrics["val_ssim"] <= 1
    # the protocol's head-only and face PSNR, and the novel views synth writes (+-20 deg here)
    assert 0 < metrics["val_psnr_head"] < metrics["val_psnr"] and 0 < metrics["val_psnr_face"] < 60
    assert metrics["novel_yaw+20_frames"] >= 1 and 5 < metrics["novel_yaw+20_psnr"] < 60
    assert "val_akd_px" in metrics and metrics["val_landmark_frames"] <= metrics["val_frames"]
    for name in ("progress.png", "metrics.json", "losses.csv", "checkpoint.safetensors", "geometry.safetensors",
                 "val_worst.png", "novel_views.png", "run.json", "assets/tracking.safetensors", "assets/dataset.json"):
        assert (run / name).is_file(), name
    assert str(dataset.parent) not in (run / "run.json").read_text()  # no absolute paths
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
    avatar = load_run(run).avatar
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
    # headforge eval RUN SUBJECT --protocol scores the held-out frames and the novel views again, as the fit did
    res = runner.invoke(app, ["eval", str(run), str(dataset), "--protocol", "--json", "-o", str(tmp_path / "rescored")])
    assert res.exit_code == 0, res.output
    rescored = json.loads(res.stdout.strip().splitlines()[-1])
    assert rescored["novel_yaw+20_psnr"] == pytest.approx(metrics["novel_yaw+20_psnr"], abs=1e-3)
    assert (tmp_path / "rescored" / "novel_views.png").is_file()


def test_nha_bad_inputs(tmp_path, tiny_config):
    from headforge.avatars.engine import fit
    from headforge.avatars.run import load_run
    from headforge.cli import app

    with pytest.raises(HeadforgeError, match="not a headforge run"):
        load_run(tmp_path)
    # a run folder of the code before the platform (config.json with the dataset's path) is refused
    (tmp_path / "config.json").write_text(json.dumps({"format": "headforge-run", "method": "nha", "dataset": "/x"}))
    with pytest.raises(HeadforgeError, match="earlier headforge .*re-run headforge fit"):
        load_run(tmp_path)
    (tmp_path / "config.json").unlink()
    (tmp_path / "run.json").write_text(json.dumps({"format": "headforge-run", "version": 2, "method": "point"}))
    with pytest.raises(HeadforgeError, match="unknown avatar method 'point'"):
        load_run(tmp_path)
    with pytest.raises(HeadforgeError, match="not a nha run"):
        load_run(tmp_path, method="nha")
    newer = {"format": "headforge-run", "version": 2, "method": "nha", "config": {"hair_cards": 3}}
    (tmp_path / "run.json").write_text(json.dumps(newer))
    with pytest.raises(HeadforgeError, match="another headforge version .*hair_cards"):
        load_run(tmp_path)
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(HeadforgeError, match="not valid JSON"):
        load_run(tmp_path)
    with pytest.raises(HeadforgeError, match="not a headforge dataset"):
        fit("nha", tmp_path / "nothing", tmp_path / "run", tiny_config, log=lambda m: None)
    res = CliRunner().invoke(app, ["fit", "nha", str(tmp_path), "-o", str(tmp_path / "r"), "--preset", "fast"])
    assert res.exit_code != 0 and "--preset" in str(res.exception)
    res = CliRunner().invoke(app, ["fit", "pointy", str(tmp_path), "-o", str(tmp_path / "r")])
    assert res.exit_code != 0 and "unknown avatar method 'pointy'" in str(res.exception)
    for bad, message in (("tex_grids=256", "NHAConfig field"), ("tex_grid=big", "not a int"), ("subdivide=maybe", "not a bool")):
        res = CliRunner().invoke(app, ["fit", "nha", str(tmp_path), "-o", str(tmp_path / "r"), "--set", bad])
        assert res.exit_code != 0 and message in str(res.exception)
    assert not (tmp_path / "r").exists()


def test_learning_rates_decay_along_a_half_cosine_at_the_end():
    from headforge.avatars.engine import lr_factor
    from headforge.avatars.nha.config import NHAConfig

    config = NHAConfig.quick()  # 4000 iterations, decay from 2800
    assert config.total_iters == 4000 and config.lr_decay_start == 0.7
    factors = [lr_factor(it, config) for it in range(config.total_iters + 1)]
    assert factors[:2801] == [1.0] * 2801
    assert all(a >= b for a, b in zip(factors, factors[1:])) and factors[-1] == pytest.approx(config.lr_final)
    assert factors[3400] == pytest.approx((1 + config.lr_final) / 2)  # half way down
    config.override("lr_final=1.0")
    assert {lr_factor(it, config) for it in range(config.total_iters + 1)} == {1.0}


def test_config_overrides_parse_as_the_field_types():
    from headforge.avatars.nha.config import NHAConfig

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


def record_chunks(monkeypatch, steps_field: str, die_at: int) -> tuple[list, dict]:
    """Patch the engine's ``fit_frames`` to record the ``rows`` of each call made with
    ``cfg.<steps_field>`` steps and a row chunk (the training-frame alignment: align_steps; the
    held-out frames' test-time fitting: tto_steps) and to raise KeyboardInterrupt (a kill) on
    the ``die["at"]``-th such call. Returns (chunks, die)."""
    from headforge.avatars import engine

    real = engine.fit_frames
    chunks, die = [], {"at": die_at}

    def recording(method, avatar, data, cfg, steps, photometric_steps=0, rows=None):
        if rows is not None and steps == getattr(cfg, steps_field):
            chunks.append(rows.tolist())
            if len(chunks) == die["at"]:
                raise KeyboardInterrupt
        return real(method, avatar, data, cfg, steps, photometric_steps, rows)

    monkeypatch.setattr(engine, "fit_frames", recording)
    return chunks, die


def test_a_run_killed_during_the_alignment_resumes_there(synth_bench, tiny_config, tmp_path, monkeypatch):
    """Alignment checkpoints every ALIGN_CHECKPOINT_FRAMES frames: a kill in the middle of it
    loses at most that many frames' alignment, and the resumed run aligns only the rest."""
    from headforge.avatars.engine import fit
    from headforge.avatars.nha import method

    dataset = synth_bench[0] / "subject_00"
    config = type(tiny_config)(**{**tiny_config.__dict__, "align_steps": 1, "tto_steps": 2})
    monkeypatch.setattr(method, "ALIGN_CHECKPOINT_FRAMES", 4)
    chunks, die = record_chunks(monkeypatch, "align_steps", die_at=2)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        fit("nha", dataset, run, config, log=lambda m: None)
    state = json.loads((run / "state.json").read_text())
    assert (state["iteration"], state["aligned"]) == (config.geometry_iters, 4)
    chunks.clear()
    die["at"] = -1
    logs = []
    fit("nha", dataset, run, config, log=logs.append)
    n_train = len(FrameData(dataset, "train", config.resolution))
    assert chunks[0] == [4, 5, 6, 7] and chunks[-1][-1] == n_train - 1 and len(chunks) == -(-(n_train - 4) // 4)
    assert any(f"aligning training frames 4..{n_train}" in m for m in logs)
    assert json.loads((run / "state.json").read_text())["aligned"] == n_train


def test_a_run_killed_during_the_test_time_fitting_resumes_there(synth_bench, tiny_config, tmp_path, monkeypatch):
    """The held-out frames' test-time fitting checkpoints every TTO_CHECKPOINT_FRAMES frames: a
    kill in the middle of it keeps the frames fitted so far, and the resumed run neither trains
    nor fits the matte again, fits only the remaining frames and then writes the metrics."""
    from headforge.avatars import engine
    from headforge.avatars.nha import method
    from headforge.avatars.run import load_run

    dataset = synth_bench[0] / "subject_00"
    config = type(tiny_config)(**{**tiny_config.__dict__, "align_steps": 1, "tto_steps": 2})
    monkeypatch.setattr(engine, "TTO_CHECKPOINT_FRAMES", 4)
    chunks, die = record_chunks(monkeypatch, "tto_steps", die_at=2)
    real_matte, mattes = method.fit_matte, []

    def counting_matte(*args, **kwargs):
        mattes.append(1)
        return real_matte(*args, **kwargs)

    monkeypatch.setattr(method, "fit_matte", counting_matte)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        engine.fit("nha", dataset, run, config, log=lambda m: None)
    state = json.loads((run / "state.json").read_text())
    assert (state["iteration"], state["tested"]) == (config.total_iters, 4)
    assert not (run / "metrics.json").exists() and len(mattes) == 1
    killed = load_run(run).avatar
    fitted, sigma = killed.frames["expression"].detach().clone(), float(killed.matte_sigma)
    chunks.clear()
    die["at"] = -1
    losses_before = (run / "losses.csv").read_text()
    metrics = engine.fit("nha", dataset, run, config, log=lambda m: None)
    val = FrameData(dataset, "val", config.resolution)
    n_val = len(val)
    assert n_val > 4 and [r for c in chunks for r in c] == list(range(4, n_val))  # only the rest, once
    assert len(mattes) == 1 and (run / "losses.csv").read_text() == losses_before  # no training, no new matte
    assert json.loads((run / "metrics.json").read_text())["val_psnr"] == metrics["val_psnr"]
    assert metrics["matte_sigma_px"] == pytest.approx(sigma)
    resumed = load_run(run).avatar.frames["expression"].detach()
    first = val.index[:4]  # the frames fitted before the kill keep their parameters
    assert torch.equal(resumed[first], fitted[first])


def test_soft_matte_changes_only_the_edge(synth_bench, tiny_config):

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


def test_in_training_validation_fits_for_val_tto_steps_and_restores_the_frames(monkeypatch):
    from types import SimpleNamespace

    from headforge.avatars import engine
    from headforge.avatars.nha.config import NHAConfig

    config = NHAConfig.quick()
    assert config.val_tto_steps < config.tto_steps
    calls = []

    def fake_fit(method, avatar, data, cfg, steps, photometric_steps=0, rows=None):
        calls.append(steps)
        avatar.frames["expression"][data.index] += 1.0  # the fitting moves the held-out frames

    monkeypatch.setattr(engine, "fit_frames", fake_fit)
    monkeypatch.setattr(engine, "score", lambda method, avatar, data, cfg, out_dir=None: ({"psnr": 0.0}, {}))
    avatar = SimpleNamespace(frames={"expression": torch.zeros(5, 3)})
    data = SimpleNamespace(index=torch.tensor([1, 3]))
    engine.validate(None, avatar, data, config)
    assert calls == [config.val_tto_steps]
    assert avatar.frames["expression"].abs().sum() == 0  # validate restored its fit


def test_gt_supervision_feeds_nhas_normal_and_semantic_terms_on_training_frames_only(synth_bench, tiny_config):
    """--supervision gt: a synth subject's training frames carry its GT landmarks (in place of
    the detections), normal and label maps; the normal and semantic terms train the geometry
    from them; the validation frames (test-time fitting) get none of it."""
    from safetensors.numpy import load_file

    from headforge.avatars.nha.method import losses

    dataset = synth_bench[0] / "subject_00"
    res = tiny_config.resolution
    train = FrameData(dataset, "train", res, supervision="gt")
    val = FrameData(dataset, "val", res, supervision="gt")
    assert "gt_known" not in val.batch(torch.arange(2)) and train.gt_known.all()
    gt = load_file(str(dataset / "gt/landmarks.safetensors"))["landmarks"]
    scale = res / 224
    expected = (torch.from_numpy(gt[train.index.numpy()]) + 0.5) * scale - 0.5
    assert torch.allclose(train.landmarks, expected)
    predicted = FrameData(dataset, "train", res)
    assert not torch.allclose(predicted.landmarks, train.landmarks)  # the detections are another thing
    avatar, _ = build_avatar(dataset, tiny_config)
    batch = train.batch(torch.arange(2))
    assert batch["gt_normals"].shape == (2, res, res, 3) and batch["gt_labels"].max() > 0
    terms = losses(avatar, batch, train.K, tiny_config, "geometry")
    assert terms["normal"] > 0 and terms["normal_abs"] > 0 and terms["classes"] > 0
    avatar.zero_grad()
    (terms["normal"] + terms["normal_abs"] + terms["classes"]).backward()
    assert avatar.geometry_net.embedding.grad.abs().sum() > 0
    without_gt = losses(avatar, predicted.batch(torch.arange(2)), train.K, tiny_config, "geometry")
    assert "normal" not in without_gt and "normal_abs" not in without_gt
    with pytest.raises(HeadforgeError, match="supervision must be"):
        FrameData(dataset, "train", res, supervision="oracle")


def test_the_normal_and_semantic_terms_vanish_on_their_own_ground_truth():
    """E_normal of a normal map against itself is 0 and grows with a bump the render lacks, but
    is blind to a tilted plane, which the absolute normal term sees;
    E_semantic of class maps that are the labels' own regions is 0."""
    from headforge.avatars.nha.method import GT_LABELS_OF_CLASS, normal_term, semantic_gt_term
    from headforge.avatars.supervision import normal_abs_term
    from headforge.avatars.nha.model import SEMANTIC_CLASSES

    yy, xx = torch.meshgrid(torch.linspace(-1, 1, 32), torch.linspace(-1, 1, 32), indexing="ij")
    inside = (xx ** 2 + yy ** 2 < 0.8)[None]
    z = -(1 - (xx ** 2 + yy ** 2).clamp(max=1)).sqrt()
    normals = torch.nn.functional.normalize(torch.stack([xx, yy, z], -1), dim=-1)[None] * inside[..., None]
    area = torch.ones_like(inside)
    assert normal_term(normals, normals, inside, area) == 0
    bump = normals.clone()
    bump[0, 14:18, 14:18, 0] += 0.3
    assert normal_term(normals, torch.nn.functional.normalize(bump, dim=-1), inside, area) > 0.01
    # a flat plane tilted 30 degrees against a flat plane: E_normal cannot see it, the absolute term does
    flat = torch.zeros_like(normals)
    flat[..., 2] = -1
    tilted = torch.zeros_like(normals)
    tilted[..., 0], tilted[..., 2] = 0.5, -(0.75 ** 0.5)
    assert normal_term(flat, tilted, inside, area) < 1e-6
    assert normal_abs_term(flat, flat, inside, area) == 0
    assert normal_abs_term(flat, tilted, inside, area) > 0.5
    labels = torch.zeros(1, 32, 32, dtype=torch.long)
    labels[0, :16] = GT_LABELS_OF_CLASS["hair"][0]
    labels[0, 16:] = GT_LABELS_OF_CLASS["skin"][0]
    labels[0, 20:22, 10:12] = GT_LABELS_OF_CLASS["eyes"][0]
    labels[0, 28:, 14:18] = 5  # the mouth's inside: in no class, not scored
    classes = torch.stack([torch.isin(labels, torch.tensor(GT_LABELS_OF_CLASS[n])) for n in SEMANTIC_CLASSES], -1).float()
    assert semantic_gt_term(classes, labels, area) == 0
    wrong = classes.clone()
    wrong[0, 28:, 14:18] = 0.7  # anything over the mouth's inside costs nothing
    assert semantic_gt_term(wrong, labels, area) == 0
    wrong[0, :4] = classes[0, -1:].expand(4, -1, -1)  # the top rows called skin instead of hair
    assert semantic_gt_term(wrong, labels, area) > 0


def test_classes_voted_from_the_gt_labels_agree_with_them_better_than_the_template_regions(synth_bench, tiny_config):
    """semantic_classes=labels: the template vertices take the class of the GT labels they are
    seen on (the subject's hairline instead of the template's), so at the tracked pose the
    semantic term against those labels drops; the mouth's inside stays in no class."""
    from headforge.avatars.nha.method import classes_from_labels, semantic_gt_term

    dataset = synth_bench[0] / "subject_00"
    res = tiny_config.resolution
    train = FrameData(dataset, "train", res, supervision="gt")
    avatar, _ = build_avatar(dataset, tiny_config)
    template = avatar.semantic_classes().clone()
    batch = train.batch(torch.arange(len(train)))
    cameras = _cameras(train.K, len(train), res)

    def term():
        with torch.no_grad():
            r = avatar.render(avatar.frame_params(batch["index"]), cameras, classes=True, matte=False, texture=False)
        return float(semantic_gt_term(r.classes, batch["gt_labels"], torch.ones_like(batch["gt_labels"], dtype=torch.bool)))

    before = term()
    table = classes_from_labels(avatar, train, tiny_config)
    assert (table != template).any(1).sum() > 10
    mouth = avatar.head.region("mouth_interior")
    assert (table[mouth] == 0).all() and ((table.sum(1) == 1) | (table.sum(1) == 0)).all()
    avatar.set_semantic_classes(table)
    assert term() < 0.8 * before
    with pytest.raises(HeadforgeError, match="semantic class table"):
        avatar.set_semantic_classes(table[:10])


def test_a_run_votes_its_semantic_classes_once_and_a_resumed_run_keeps_them(synth_bench, tiny_config, tmp_path,
                                                                            interrupt_after):
    """--supervision gt with semantic_classes=labels: the first iteration votes the table (logged,
    kept in state.json); a resumed run takes it from there instead of voting again."""
    from dataclasses import replace

    from headforge.avatars.engine import fit

    dataset = synth_bench[0] / "subject_00"
    config = replace(tiny_config, supervision="gt", semantic_classes="labels")
    run = tmp_path / "run"
    logs = []
    with pytest.raises(KeyboardInterrupt):
        fit("nha", dataset, run, config, log=logs.append, progress=interrupt_after(3))
    assert sum("semantic classes from the GT labels" in m for m in logs) == 1
    saved = json.loads((run / "state.json").read_text())["semantic_classes"]
    assert len(saved) == 4570 and {-1, 0, 1, 2} >= set(saved) and saved.count(2) > 250  # more hair than the crown
    logs.clear()
    fit("nha", dataset, run, config, log=logs.append)
    assert not any("semantic classes from the GT labels" in m for m in logs)
    assert json.loads((run / "state.json").read_text())["semantic_classes"] == saved


def test_held_out_detections_are_corrected_by_the_detector_bias_of_the_training_frames(synth_bench, tiny_config):
    """--supervision gt trains on ground-truth landmarks and fits the held-out frames to
    detections: the detector's mean offset from the ground truth, measured on the training frames
    only, is taken off the held-out detections (their face ovals redrawn)."""
    from headforge.avatars.frames import detector_bias

    dataset = synth_bench[0] / "subject_00"
    res = tiny_config.resolution
    train = FrameData(dataset, "train", res, supervision="gt")
    detected = FrameData(dataset, "train", res).landmarks
    bias = train.detector_bias
    ok = torch.isfinite(detected).all(-1)
    assert bias.shape == (478, 2) and bias.abs().max() > 0.1
    k = int(ok.sum(0).argmax())
    assert torch.allclose(bias[k], (detected[ok[:, k], k] - train.landmarks[ok[:, k], k]).mean(0), atol=1e-5)
    assert FrameData(dataset, "train", res).detector_bias is None  # nothing to measure without ground truth
    val = FrameData(dataset, "val", res)
    before = val.landmarks.clone()
    val.correct_detections(bias)
    assert torch.allclose(torch.nan_to_num(before - val.landmarks), bias.expand_as(before) * torch.isfinite(before), atol=1e-4)
    with pytest.raises(HeadforgeError, match="landmark bias"):
        val.correct_detections(bias[:10])
    two = torch.tensor([[[0.0, 0.0], [float("nan"), float("nan")]], [[2.0, 4.0], [1.0, 1.0]]])
    assert torch.allclose(detector_bias(two, torch.zeros_like(two)), torch.tensor([[1.0, 2.0], [1.0, 1.0]]))
