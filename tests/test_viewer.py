"""``headforge view``: the server (localhost, read-only, no traversal, one-line errors) and, in
headless Chromium, the page (the avatar drawn where headforge draws it, a slider changes it) and
the exported .glb loaded by three.js's GLTFLoader."""

from __future__ import annotations

import json
import socket
import urllib.error
import urllib.request

import numpy as np
import pytest
import torch

from headforge.errors import HeadforgeError

pygltflib = pytest.importorskip("pygltflib", reason="pygltflib is a dev dependency (pip install -e '.[dev]')")


def get(url: str, method: str = "GET") -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method=method), timeout=30) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as err:
        return err.code, b""


@pytest.fixture(scope="module")
def served(open_head_nha_run):
    """The viewer of the tiny open-head NHA run on a free port of 127.0.0.1."""
    from headforge.viewer.scene import build_scene
    from headforge.viewer.server import ViewerServer

    server = ViewerServer(build_scene(open_head_nha_run, texture_size=128), port=0).start()
    yield server
    server.stop()


def test_the_server_binds_localhost_and_serves_only_its_own_files(served, open_head_nha_run):
    assert served.host == "127.0.0.1" and served.url.startswith("http://127.0.0.1:")
    status, body = get(served.url + "scene.json")
    scene = json.loads(body)
    assert status == 200 and scene["kind"] == "mesh" and len(scene["expressions"]) == 52
    assert get(served.url)[0] == 200 and get(served.url + "avatar.glb")[1][:4] == b"glTF"
    assert get(served.url + "vendor/three/three.module.js")[0] == 200
    # nothing else: no file of the run folder, no traversal, no writes
    for path in ("run.json", "../run.json", "%2e%2e/run.json", "..%2f..%2fetc%2fpasswd", "vendor/../scene.json",
                 "/etc/passwd", "static/index.html"):
        assert get(served.url + path)[0] == 404, path
    assert get(served.url + "scene.json", "POST")[0] == 405
    assert get(served.url + "scene.json", "PUT")[0] == 405
    assert (open_head_nha_run / "run.json").is_file() and not (open_head_nha_run / "avatar.glb").exists()


def test_bad_input_is_a_one_line_error(served, open_head_nha_run, tmp_path):
    import shutil

    from typer.testing import CliRunner

    from headforge.cli import app
    from headforge.viewer.scene import Scene, build_scene
    from headforge.viewer.server import ViewerServer

    with pytest.raises(HeadforgeError, match="is in use"):
        ViewerServer(Scene({"kind": "mesh"}), port=served.port)
    with pytest.raises(HeadforgeError, match="does not exist"):
        build_scene(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(HeadforgeError, match="neither a run folder"):
        build_scene(tmp_path / "empty")
    unknown = tmp_path / "unknown"
    shutil.copytree(open_head_nha_run, unknown)
    info = json.loads((unknown / "run.json").read_text())
    (unknown / "run.json").write_text(json.dumps({**info, "method": "nosuch"}))
    with pytest.raises(HeadforgeError, match="unknown avatar method 'nosuch'"):
        build_scene(unknown)
    # through the command: exit 1, one line
    for args in ([str(tmp_path / "nothing")], [str(unknown)], [str(open_head_nha_run), "--port", str(served.port)]):
        res = CliRunner().invoke(app, ["view", *args])
        assert res.exit_code == 1 and isinstance(res.exception, (HeadforgeError, SystemExit)), res.output


def test_a_tracked_dataset_and_a_headcraft_map_are_viewed_as_meshes(open_head_nha_run, tmp_path):
    import trimesh

    from headforge.viewer.scene import build_scene

    data = open_head_nha_run.parent / "data"
    scene = build_scene(data)
    assert scene.manifest["kind"] == "mesh" and scene.manifest["frames"] == 6 and scene.manifest["K"] is not None
    g = pygltflib.GLTF2.load_from_bytes(scene.files["avatar.glb"])
    assert len(g.animations) == 1 and len(g.meshes[0].primitives[0].targets) == 52 and len(g.skins) == 1
    # a HeadCraft map folder: its registered mesh, static
    (tmp_path / "map").mkdir()
    trimesh.creation.icosphere(subdivisions=2, radius=0.1).export(tmp_path / "map" / "registered.ply")
    scene = build_scene(tmp_path / "map")
    g = pygltflib.GLTF2.load_from_bytes(scene.files["avatar.glb"])
    assert scene.manifest["frames"] == 0 and not g.animations and g.accessors[0].count == 162
    (tmp_path / "map" / "registered.ply").write_text("not a mesh")
    with pytest.raises(HeadforgeError, match="registered.ply"):
        build_scene(tmp_path / "map")


# ---- in the browser ----------------------------------------------------------------------------------
def browser_or_skip():
    from headforge.viewer import browser

    reason = browser.missing()
    if reason:
        pytest.skip(f"browser test skipped: {reason}")
    return browser


def test_the_viewer_draws_the_avatar_where_headforge_does_and_a_slider_moves_it(served, open_head_nha_run):
    """Frame 0 in the page (the clip's camera) covers the pixels headforge's own render covers
    (IoU >= 0.9); moving the jawOpen slider changes the picture around the mouth."""
    browser = browser_or_skip()
    from headforge.avatars.run import load_run
    from headforge.render.camera import Cameras, scale_intrinsics

    size = 192
    r = load_run(open_head_nha_run)
    K = scale_intrinsics(r.assets.intrinsics(r.config.resolution), size / r.config.resolution)
    first = r.assets.rows("all")[:1]
    with torch.no_grad():
        coverage = r.avatar.render(r.avatar.frame_params(torch.tensor(first)), Cameras.at_origin(K, 1, size)).coverage[0]
    expected = coverage.numpy() > 0.5
    with browser.page() as page:
        browser.open_viewer(page, served.url, size)
        shown = browser.frame(page, 0)
        drawn = shown.min(-1) < 250  # anything not the white background
        assert drawn.shape == expected.shape
        iou = (drawn & expected).sum() / (drawn | expected).sum()
        assert iou >= 0.9, iou
        page.locator("#expr-jawOpen").fill("1")
        page.evaluate("window.viewer.draw()")
        moved = browser.canvas(page)
        changed = np.abs(moved.astype(int) - shown.astype(int)).max(-1) > 10
        assert changed.sum() > 30
        ys = np.nonzero(changed)[0]
        assert ys.mean() > np.nonzero(expected)[0].mean()  # below the head's centre: the mouth and chin
        assert page.errors == []


def test_three_js_loads_the_exported_glb(open_head_nha_run, tmp_path):
    """GLTFLoader in headless Chromium reads ``headforge export --format glb``: one skinned mesh,
    one skin of five joints, 52 morph targets with the ARKit names, one animation with a track
    per joint rotation, the head's translation and the morph weights."""
    browser = browser_or_skip()
    from typer.testing import CliRunner

    from headforge.cli import app
    from headforge.viewer.scene import Scene
    from headforge.viewer.server import ViewerServer

    res = CliRunner().invoke(app, ["export", str(open_head_nha_run), "-o", str(tmp_path), "--format", "glb",
                                   "--texture-size", "64"])
    assert res.exit_code == 0, res.output
    glb = (tmp_path / "avatar.glb").read_bytes()
    # the viewer's three.js files, with the exported file and a bare page beside them
    probe = b"""<!doctype html><script type="importmap">{"imports": {"three": "./vendor/three/three.module.js",
        "three/addons/": "./vendor/three/addons/"}}</script>"""
    server = ViewerServer(Scene({}, {"export.glb": glb, "probe.html": probe}), port=0).start()
    try:
        with browser.page() as page:
            page.goto(server.url + "probe.html")
            counts = page.evaluate("""async () => {
                const { GLTFLoader } = await import('./vendor/three/addons/loaders/GLTFLoader.js');
                const gltf = await new GLTFLoader().loadAsync('export.glb');
                let meshes = 0, skinned = 0, targets = 0, joints = 0, names = [];
                gltf.scene.traverse((o) => {
                  if (o.isMesh) { meshes += 1; targets = o.morphTargetInfluences.length;
                                  names = Object.keys(o.morphTargetDictionary); }
                  if (o.isSkinnedMesh) { skinned += 1; joints = o.skeleton.bones.length; }
                });
                return { meshes, skinned, targets, joints, names, skins: gltf.parser.json.skins.length,
                         animations: gltf.animations.length, tracks: gltf.animations[0].tracks.length,
                         duration: gltf.animations[0].duration, map: !!gltf.scene.getObjectByName('mesh').material.map };
            }""")
            assert page.errors == []
    finally:
        server.stop()
    assert counts["meshes"] == 1 and counts["skinned"] == 1 and counts["skins"] == 1 and counts["joints"] == 5
    assert counts["targets"] == 52 and "jawOpen" in counts["names"] and counts["map"]
    assert counts["animations"] == 1 and counts["tracks"] == 7
    assert counts["duration"] == pytest.approx(5 / 25, abs=1e-6)  # six frames at the dataset's 25 fps


def test_a_point_avatar_exports_its_sequence_and_is_viewed_relightable(rendered, tiny_head, tmp_path):
    """A PointAvatar run: ``export --format ply --driving DATASET`` writes one posed PLY per driving
    frame; the viewer shows the points over their frames, and in the browser the light-direction
    slider changes the picture (Lambert on the albedo)."""
    import sys
    from pathlib import Path

    from typer.testing import CliRunner

    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import write_rendered_dataset
    from test_pointavatar import tiny_config

    from headforge.avatars.engine import fit
    from headforge.cli import app
    from headforge.viewer.scene import build_scene
    from headforge.viewer.server import ViewerServer

    run = tmp_path / "run"
    fit("pointavatar", rendered, run, tiny_config(iterations=6), log=lambda m: None)
    other = write_rendered_dataset(tmp_path / "other", tiny_head, frames=4, val=1, seed=1)
    res = CliRunner().invoke(app, ["export", str(run), "-o", str(tmp_path / "ply"), "--format", "ply",
                                   "--driving", str(other)])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "ply" / "sequence").iterdir()) == [f"{t:05d}.ply" for t in range(4)]
    scene = build_scene(run)
    m = scene.manifest
    assert m["kind"] == "points" and m["relightable"] and m["frames"] == 8
    N = m["points"]
    assert len(scene.files["points.bin"]) == 8 * N * 24 + (-(-(N * 3) // 4) * 4) + 4 * N
    browser = browser_or_skip()
    server = ViewerServer(scene, port=0).start()
    try:
        with browser.page() as page:
            browser.open_viewer(page, server.url, 128)
            lit = browser.frame(page, 0)
            assert (lit.min(-1) < 250).sum() > 200  # the points are drawn
            page.locator("#light-azimuth").fill("2.5")
            page.evaluate("window.viewer.draw()")
            turned = browser.canvas(page)
            assert (np.abs(turned.astype(int) - lit.astype(int)).max(-1) > 10).sum() > 50
            # the neck slider: the server poses the points (PointPoser), the page draws them
            page.locator("#joint-neck-y").fill("0.8")
            page.wait_for_function("window.viewer.poses >= 1", timeout=60_000)
            page.evaluate("window.viewer.draw()")
            posed = browser.canvas(page)
            assert (np.abs(posed.astype(int) - turned.astype(int)).max(-1) > 10).sum() > 50
            assert page.errors == []
    finally:
        server.stop()
    poser = scene.handlers["pose"]
    moved = np.frombuffer(poser({"frame": "0", "neck": "0,0.8,0", "expression": "0:1"}), "<f4").reshape(2, N, 3)
    still = np.frombuffer(poser({"frame": "0"}), "<f4").reshape(2, N, 3)
    assert np.abs(moved[0] - still[0]).max() > 0.005 and np.allclose(np.linalg.norm(still[1], axis=1), 1, atol=1e-3)
    for bad in ({"frame": "8"}, {"frame": "0", "neck": "1,2"}, {"frame": "0", "expression": "9:1"}):
        with pytest.raises(ValueError):
            poser(bad)
    server = ViewerServer(scene, port=0).start()
    try:
        assert get(server.url + "pose?frame=99")[0] == 400 and get(server.url + "x/pose")[0] == 404
    finally:
        server.stop()


def test_the_view_command_serves_until_interrupted(open_head_nha_run):
    """``headforge view RUN --port 0`` prints its URL (on 127.0.0.1) and serves the scene until
    it is interrupted."""
    import signal
    import subprocess
    import sys

    # a shell without job control starts background commands with SIGINT ignored, and a child
    # inherits that (Python then installs no KeyboardInterrupt handler): give it Ctrl-C back, as a
    # terminal would, so the test also runs under `nohup ... &`
    proc = subprocess.Popen([sys.executable, "-m", "headforge.cli", "view", str(open_head_nha_run), "--port", "0",
                             "--texture-size", "32"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:"), url
        status, body = get(url + "scene.json")
        assert status == 200 and json.loads(body)["kind"] == "mesh"
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            assert proc.wait(timeout=30) == 0
        finally:
            proc.kill()  # never leave a server behind when it did not stop
