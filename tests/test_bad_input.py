"""Bad input to the lower-level commands (track, synth, eval, model fit-image, render turntable)
and to the dataset reader: each ends in one HeadforgeError that names the file or option (the
CLI prints it on one line and exits 1), and nothing that looks complete is written.

The test data is tiny and made here: noise clips, a few PNGs, a hand-written dataset and synth
subject whose files are then broken."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from headforge.cli import app
from headforge.errors import HeadforgeError


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def assert_refused(res, *names) -> str:
    """A non-zero exit through a one-line HeadforgeError mentioning every one of ``names``."""
    assert res.exit_code != 0, res.output
    assert isinstance(res.exception, HeadforgeError), repr(res.exception)
    message = str(res.exception)
    assert "\n" not in message, message
    for name in names:
        assert str(name) in message, (name, message)
    return message


def noise_video(path: Path, frames: int = 3, size: int = 64, fps: float = 10.0) -> Path:
    from headforge.render.io import write_mp4

    rng = np.random.default_rng(0)
    return write_mp4(path, [rng.integers(0, 255, (size, size, 3), dtype=np.uint8) for _ in range(frames)], fps=fps)


def write_pngs(folder: Path, n: int, size=(64, 64), grey: bool = False) -> Path:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    for i in range(n):
        shape = size[::-1] if grey else (*size[::-1], 3)
        Image.fromarray(rng.integers(0, 255, shape, dtype=np.uint8)).save(folder / f"{i:05d}.png")
    return folder


def tiny_dataset(root: Path, frames: int = 4, resolution: int = 32) -> Path:
    """A dataset in the format headforge track writes (noise images, zero parameters)."""
    import torch
    from safetensors.torch import save_file

    write_pngs(root / "frames", frames, (resolution, resolution))
    write_pngs(root / "masks", frames, (resolution, resolution), grey=True)
    T = frames
    tracking = {"shape": torch.zeros(1, 4), "expression": torch.zeros(T, 3), "translation": torch.zeros(T, 3),
                "landmarks": torch.zeros(T, 10, 2), "valid": torch.ones(T, dtype=torch.bool),
                **{k: torch.zeros(T, 3) for k in ("root_pose", "neck_pose", "jaw_pose", "eye_left_pose", "eye_right_pose")}}
    save_file(tracking, str(root / "tracking.safetensors"))
    records = [{"index": t, "source_frame": t, "valid": True, "split": "val" if t == T - 1 else "train",
                "image": f"frames/{t:05d}.png", "mask": f"masks/{t:05d}.png", "crop": [16, 16, 32]} for t in range(T)]
    meta = {"format": "headforge-dataset", "version": 1, "model": "open-head", "n_shape": 4, "resolution": resolution,
            "fps": 25.0, "intrinsics": [[64.0, 0, 15.5], [0, 64.0, 15.5], [0, 0, 1]], "frames": records}
    (root / "dataset.json").write_text(json.dumps(meta))
    return root


def tiny_subject(root: Path) -> Path:
    """A stand-in ``headforge synth`` subject: gt/geometry.safetensors (one triangle), gt/subject.json."""
    from safetensors.numpy import save_file

    (root / "gt").mkdir(parents=True)
    tri = np.array([[[-0.1, -0.1, 0.5], [0.1, -0.1, 0.5], [0.0, 0.1, 0.5]]], np.float32)
    save_file({"frames": np.array([0, 1]), "vertices": np.repeat(tri, 2, 0), "faces": np.array([[0, 1, 2]]),
               "labels": np.ones(3, np.uint8)}, str(root / "gt" / "geometry.safetensors"))
    info = {"train_frames": 0, "intrinsics": [[64.0, 0, 15.5], [0, 64.0, 15.5], [0, 0, 1]], "resolution": 32,
            "labels": {"face": 1, "hair": 3}, "head_labels": [1], "subject": {"hair_style": "short"}}
    (root / "gt" / "subject.json").write_text(json.dumps(info))
    return root


def exported_prediction(root: Path) -> Path:
    from safetensors.numpy import save_file

    root.mkdir(parents=True)
    tri = np.array([[[-0.1, -0.1, 0.5], [0.1, -0.1, 0.5], [0.0, 0.1, 0.5]]], np.float32)
    save_file({"frames": np.array([0, 1]), "vertices": np.repeat(tri, 2, 0), "faces": np.array([[0, 1, 2]]),
               "face_vertices": np.ones(3, bool), "head_vertices": np.ones(3, bool)},
              str(root / "geometry.safetensors"))
    return root


@pytest.fixture
def clip(tmp_path):
    return noise_video(tmp_path / "noise.mp4")


# -- headforge track: options ---------------------------------------------------------------


@pytest.mark.parametrize("args, option", [
    (["--every", "0"], "--every"), (["--every", "-3"], "--every"),
    (["--resolution", "16"], "--resolution"), (["--resolution", "100000"], "--resolution"),
    (["--val-fraction", "1"], "--val-fraction"), (["--val-fraction", "-0.1"], "--val-fraction"),
    (["--val-fraction", "nan"], "--val-fraction"),
    (["--max-frames", "0"], "--max-frames"),
    (["--focal", "0"], "--focal"), (["--focal", "-100"], "--focal"), (["--focal", "inf"], "--focal"),
    (["--crop", "other"], "--crop"), (["--preset", "other"], "--preset"),
    (["--masks", "/nonexistent/masks"], "/nonexistent/masks"),
    (["--model", "nope"], "--model"),
])
def test_track_refuses_out_of_range_options_before_any_work(clip, tmp_path, args, option):
    out = tmp_path / "ds"
    assert_refused(invoke("track", clip, "-o", out, *args), option)
    assert not out.exists() and not out.with_name("ds.partial").exists()


def test_track_options_are_checked_in_the_library_too():
    from headforge.track.pipeline import TrackOptions

    with pytest.raises(HeadforgeError, match="--every must be >= 1, got 0"):
        TrackOptions(every=0).validate()
    with pytest.raises(HeadforgeError, match="--fps must be > 0"):
        TrackOptions(fps=0).validate()


def test_the_command_line_prints_one_line_without_a_traceback(clip, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "headforge.cli", "track", str(clip), "-o", str(tmp_path / "ds"),
                           "--every", "0"], capture_output=True, text=True)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "--every must be >= 1, got 0" in lines[0], proc.stderr


# -- headforge track: sources ---------------------------------------------------------------


def test_track_refuses_missing_empty_and_undecodable_videos(tmp_path):
    missing = tmp_path / "missing.mp4"
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\x00garbage, not a video" * 64)
    truncated = tmp_path / "truncated.mp4"
    truncated.write_bytes(noise_video(tmp_path / "whole.mp4").read_bytes()[:200])
    for video, words in ((missing, ("not found", missing)), (empty, ("empty", empty)),
                         (junk, ("cannot decode", junk)), (truncated, (truncated,))):
        out = tmp_path / f"ds_{video.stem}"
        assert_refused(invoke("track", video, "-o", out), *words)
        assert not (out / "dataset.json").exists()


def test_track_refuses_a_video_without_a_face(clip, tmp_path):
    out = tmp_path / "ds"
    assert_refused(invoke("track", clip, "-o", out, "--no-overlay"), "no face found in any of the 3 frames", clip)
    assert not out.exists() and not out.with_name("ds.partial").exists()


def test_track_refuses_bad_frame_folders(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no images here")
    corrupt = write_pngs(tmp_path / "corrupt", 2)
    (corrupt / "00000.png").write_bytes(b"not a png")
    mixed = write_pngs(tmp_path / "mixed", 2)
    write_pngs(tmp_path / "mixed_big", 1, (80, 64))
    (tmp_path / "mixed_big" / "00000.png").replace(mixed / "00001.png")
    for folder, words in ((empty, ("no PNG/JPEG frames", empty)), (corrupt, ("cannot read image", "00000.png")),
                          (mixed, ("00001.png", "80x64", "64x64"))):
        out = tmp_path / f"ds_{folder.name}"
        assert_refused(invoke("track", folder, "-o", out), *words)
        assert not (out / "dataset.json").exists()


def test_track_refuses_masks_that_do_not_fit_the_frames(clip, tmp_path):
    few = write_pngs(tmp_path / "few", 1, grey=True)
    small = write_pngs(tmp_path / "small", 3, (32, 32), grey=True)
    for masks, words in ((few, ("--masks", "1 images", "3 frames")), (small, ("32x32", "64x64"))):
        out = tmp_path / f"ds_{masks.name}"
        assert_refused(invoke("track", clip, "-o", out, "--masks", masks), *words)
        assert not out.exists()


def test_track_refuses_an_output_that_is_a_file(clip, tmp_path):
    out = tmp_path / "ds"
    out.write_text("a file")
    assert_refused(invoke("track", clip, "-o", out), out, "a file")


# -- datasets: a broken tracking.safetensors, missing or broken frames ----------------------


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty", "key missing"])
def test_a_broken_tracking_file_is_named(tmp_path, damage):
    import torch
    from safetensors.torch import load_file, save_file

    from headforge.data.dataset import HeadDataset

    root = tiny_dataset(tmp_path / "ds")
    path = root / "tracking.safetensors"
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:-40])
    elif damage == "garbage":
        path.write_bytes(np.random.default_rng(0).bytes(3000))
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        tracking = load_file(str(path))
        del tracking["jaw_pose"]
        save_file(tracking, str(path))
    with pytest.raises(HeadforgeError, match="tracking.safetensors") as info:
        HeadDataset(root, "train")
    assert "\n" not in str(info.value)
    # headforge eval reads the tracked model of a dataset: the same one-line error, no report
    subject = tiny_subject(tmp_path / "subject")
    assert_refused(invoke("eval", root, subject, "-o", tmp_path / "eval"), path)
    assert not (tmp_path / "eval").exists()
    del torch


def test_tracking_that_does_not_cover_the_frames_is_named(tmp_path):
    from safetensors.torch import load_file, save_file

    from headforge.data.dataset import HeadDataset

    root = tiny_dataset(tmp_path / "ds")
    tracking = load_file(str(root / "tracking.safetensors"))
    save_file({k: v if k == "shape" else v[:2].contiguous() for k, v in tracking.items()}, str(root / "tracking.safetensors"))
    with pytest.raises(HeadforgeError, match="4 frames"):
        HeadDataset(root, "all")


@pytest.mark.parametrize("kind", ["image", "mask"])
def test_a_missing_or_broken_frame_is_named_when_it_is_read(tmp_path, kind):
    from headforge.data.dataset import HeadDataset

    root = tiny_dataset(tmp_path / "ds", frames=4)
    folder = "frames" if kind == "image" else "masks"
    middle = root / folder / "00001.png"  # neither the first nor the last: found when the item is read
    middle.unlink()
    train = HeadDataset(root, "train")
    assert train[0]["image"].shape == (32, 32, 3)
    with pytest.raises(HeadforgeError, match="00001.png is missing"):
        train[1]
    middle.write_bytes(b"\x89PNG\r\n\x1a\n broken")
    with pytest.raises(HeadforgeError, match="00001.png is unreadable"):
        train[1]
    write_pngs(tmp_path / "big", 1, (48, 48), grey=kind == "mask")
    (tmp_path / "big" / "00000.png").replace(middle)
    with pytest.raises(HeadforgeError, match="00001.png is not 32x32"):
        train[1]


def test_a_broken_dataset_json_is_named(tmp_path):
    from headforge.data.dataset import HeadDataset

    root = tiny_dataset(tmp_path / "ds")
    meta = json.loads((root / "dataset.json").read_text())
    del meta["intrinsics"]
    (root / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(HeadforgeError, match="lacks 'intrinsics'"):
        HeadDataset(root)
    (root / "dataset.json").write_text("{ not json")
    with pytest.raises(HeadforgeError, match="not valid JSON"):
        HeadDataset(root)


# -- headforge synth ------------------------------------------------------------------------


@pytest.mark.parametrize("args, option", [
    (["--subjects", "0"], "--subjects"), (["--train-frames", "0"], "--train-frames"),
    (["--val-frames", "-1"], "--val-frames"), (["--resolution", "16"], "--resolution"),
    (["--resolution", "100000"], "--resolution"), (["--gt-every", "0"], "--gt-every"),
    (["--train-frames", "10", "--val-frames", "5", "--gt-every", "20"], "--gt-every"),
    (["--supersample", "0"], "--supersample"), (["--supersample", "64"], "--supersample"),
    (["--seed", "-1"], "--seed"),
])
def test_synth_refuses_out_of_range_numbers_before_any_work(tmp_path, args, option):
    out = tmp_path / "bench"
    assert_refused(invoke("synth", "-o", out, *args), option)
    assert not out.exists() and not out.with_name("bench.partial").exists()


# -- headforge eval -------------------------------------------------------------------------


def test_eval_refuses_missing_folders_and_mismatched_names(tmp_path):
    pred, gt = write_pngs(tmp_path / "pred", 2), write_pngs(tmp_path / "gt", 2)
    out = tmp_path / "eval"
    assert_refused(invoke("eval", tmp_path / "nope", gt, "-o", out), tmp_path / "nope")
    assert_refused(invoke("eval", pred, tmp_path / "nope", "-o", out), tmp_path / "nope")
    assert_refused(invoke("eval", pred, gt, "--masks", tmp_path / "nope", "-o", out), "--masks", tmp_path / "nope")
    (pred / "00001.png").rename(pred / "other.png")
    assert_refused(invoke("eval", pred, gt, "-o", out), "have no prediction", "00001.png")
    (pred / "other.png").write_bytes(b"broken")
    (pred / "other.png").rename(pred / "00001.png")
    assert_refused(invoke("eval", pred, gt, "-o", out), "cannot read image", "00001.png")
    write_pngs(tmp_path / "small", 2, (32, 32))
    assert_refused(invoke("eval", tmp_path / "small", gt, "-o", out), "00000.png")
    assert not out.exists()
    report = tmp_path / "report"
    report.write_text("a file")
    assert_refused(invoke("eval", gt, gt, "-o", report), report)


@pytest.mark.parametrize("damage", ["geometry garbage", "geometry key", "subject json", "subject key", "normals missing"])
def test_eval_refuses_a_synth_subject_with_a_broken_gt(tmp_path, damage):
    from safetensors.numpy import load_file, save_file

    subject = tiny_subject(tmp_path / "subject")
    prediction = exported_prediction(tmp_path / "pred")
    gt = subject / "gt"
    if damage == "geometry garbage":
        named = gt / "geometry.safetensors"
        named.write_bytes(named.read_bytes()[:50])
    elif damage == "geometry key":
        named = gt / "geometry.safetensors"
        arrays = load_file(str(named))
        del arrays["labels"]
        save_file(arrays, str(named))
    elif damage == "subject json":
        named = gt / "subject.json"
        named.write_text("{ truncated")
    elif damage == "subject key":
        named = gt / "subject.json"
        info = json.loads(named.read_text())
        del info["intrinsics"]
        named.write_text(json.dumps(info))
    else:
        named = gt / "normals" / "00000.png"  # the first GT frame's normal map was never written
    out = tmp_path / "eval"
    assert_refused(invoke("eval", prediction, subject, "-o", out), named)
    assert not out.exists()


def test_eval_refuses_broken_exported_geometry(tmp_path):
    from safetensors.numpy import save_file

    subject = tiny_subject(tmp_path / "subject")
    prediction = exported_prediction(tmp_path / "pred")
    path = prediction / "geometry.safetensors"
    save_file({"frames": np.array([0, 1]), "vertices": np.zeros((2, 3, 3), np.float32), "faces": np.array([[0, 1, 7]]),
               "face_vertices": np.ones(3, bool), "head_vertices": np.ones(3, bool)}, str(path))
    assert_refused(invoke("eval", prediction, subject, "-o", tmp_path / "eval"), path, "outside")
    path.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{}")
    assert_refused(invoke("eval", prediction, subject, "-o", tmp_path / "eval"), path)
    assert_refused(invoke("eval", prediction, subject, "--every", "0", "-o", tmp_path / "eval"), "--every")
    assert_refused(invoke("eval", prediction, subject, "--split", "test", "-o", tmp_path / "eval"), "split")
    assert not (tmp_path / "eval").exists()


# -- headforge model fit-image and render turntable -----------------------------------------


def test_fit_image_refuses_unreadable_images(tmp_path):
    junk = tmp_path / "photo.png"
    junk.write_bytes(b"not an image at all")
    out = tmp_path / "fit.png"
    assert_refused(invoke("model", "fit-image", junk, "-o", out), "cannot read image", junk)
    assert_refused(invoke("model", "fit-image", tmp_path / "none.jpg", "-o", out), "not found")
    assert_refused(invoke("model", "fit-image", junk, "-o", out, "--steps", "0"), "--steps")
    assert not out.exists()


def test_fit_image_refuses_a_picture_without_a_face(open_head_data, tmp_path, clip):
    blank = write_pngs(tmp_path / "pics", 1, (200, 200)) / "00000.png"
    out = tmp_path / "fit.png"
    assert_refused(invoke("model", "fit-image", blank, "-o", out, "--steps", "1"), "no face found")
    assert_refused(invoke("model", "fit-image", clip, "--frame", "7", "-o", out), "fewer than 8 frames")
    assert not out.exists()


def test_render_turntable_refuses_bad_numbers_and_outputs(open_head_data, tmp_path):
    out = tmp_path / "turn.mp4"
    small = ["--frames", "1", "--resolution", "32", "--points", "100"]
    assert_refused(invoke("render", "turntable", "-o", out, "--frames", "0"), "--frames")
    assert_refused(invoke("render", "turntable", "-o", out, "--resolution", "8"), "--resolution")
    assert_refused(invoke("render", "turntable", "-o", out, "--points", "0"), "--points")
    assert_refused(invoke("render", "turntable", "-o", out, *small, "--fps", "0"), "fps")
    folder = tmp_path / "folder.mp4"
    folder.mkdir()
    assert_refused(invoke("render", "turntable", "-o", folder, *small), folder, "folder")
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder should be")
    assert_refused(invoke("render", "turntable", "-o", blocker / "turn.mp4", *small), blocker / "turn.mp4", "is a file")
    assert not out.exists() and not list(tmp_path.glob("*.partial.mp4"))


# -- resumable work folders: a checkpoint or settings file broken by a killed run ------------


def test_an_unreadable_checkpoint_is_redone_not_fatal(tmp_path):
    from headforge.data.preprocess import ClipDetections
    from headforge.track.pipeline import _load_checkpoint

    logs = []
    path = tmp_path / "detections.npz"
    path.write_bytes(b"PK\x03\x04 half-written zip")
    assert _load_checkpoint(path, ClipDetections.load, logs.append) is None
    assert not path.exists() and "detections.npz is unreadable" in logs[0]
    assert _load_checkpoint(path, ClipDetections.load, logs.append) is None and len(logs) == 1  # absent: silent


def test_a_half_written_settings_file_starts_the_run_over(tmp_path):
    from headforge.paths import open_partial

    work = tmp_path / "out.partial"
    work.mkdir()
    (work / "settings.json").write_text('{"resolution": 5')
    (work / "stale.txt").write_text("from the killed run")
    logs = []
    assert open_partial(tmp_path / "out", {"resolution": 512}, logs.append) == work
    assert not (work / "stale.txt").exists() and "starting over" in logs[0]
    assert json.loads((work / "settings.json").read_text()) == {"resolution": 512}


def test_fit_with_gt_supervision_refuses_a_dataset_without_ground_truth(rendered, tmp_path):
    """--supervision gt needs a headforge synth subject; a tracked clip (no gt/) is named in one
    line, and an unknown supervision is refused; neither leaves a run folder that looks trained."""
    run = tmp_path / "run"
    assert_refused(invoke("fit", "nha", rendered, "-o", run, "--supervision", "gt", "--iterations", "3",
                          "--device", "cpu"), "gt/landmarks.safetensors", rendered)
    assert_refused(invoke("fit", "nha", rendered, "-o", run, "--supervision", "oracle", "--iterations", "3",
                          "--device", "cpu"), "supervision", "oracle")
    assert not (run / "checkpoint.safetensors").exists() and not (run / "metrics.json").exists()
