"""Record the NHA reference losses that tests/test_platform.py checks NHA's training against.

Run once with the code *before* a change that must not alter NHA's training, or *after* a
change that alters it on purpose (say so in the commit):

    python tests/data/make_nha_reference.py COMMIT

It renders the tiny dataset of ``tests/conftest.py::write_rendered_dataset`` (no MediaPipe) of
the fixed tiny head model ``tiny_nha_head_data`` (an open-head build is not bit-identical between
builds, so a reference on it would hold on one machine's cache only), trains NHA for 50 iterations
with ``reference_settings()`` and writes every energy evaluation (training steps, per-frame
alignment, in-training validation and test-time fitting, in call order) at full precision to
``nha_reference_losses.json``. History: recorded at 64909a8 by the pre-platform trainer (the
platform move reproduced it to 1e-6); re-recorded after NHA's energies took the protocol's head
region (``headforge.avatars.nha.method.energy_area``), which changes the silhouette, outline and
photometric terms by design; re-recorded after the inner surfaces' offset penalty
(``w_offset_inner``), a new term by design.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def reference_settings() -> dict:
    """The tiny NHA run of the reference: quick preset fields changed to these values."""
    return {"resolution": 64, "geometry_iters": 16, "texture_iters": 17, "joint_iters": 17, "align_steps": 2,
            "val_every": 25, "val_frames": 2, "val_tto_steps": 1, "tto_steps": 2, "checkpoint_every": 25,
            "tex_grid": 32, "geo_width": 32, "tex_width": 32, "tex_channels": 8, "tex_layers": 2}


def use_tiny_head() -> object:
    """Make ``headforge.head.load_data("tiny-nha")`` return the tiny NHA head; returns its data."""
    import headforge.head
    from conftest import tiny_nha_head_data

    data = tiny_nha_head_data()
    original = headforge.head.load_data
    headforge.head.load_data = lambda name="open-head", *a, **k: data if name == data.name else original(name, *a, **k)
    return data


def main() -> None:
    import torch

    from conftest import write_rendered_dataset
    from headforge.avatars import engine
    from headforge.avatars.nha.config import NHAConfig
    from headforge.avatars.nha.method import NHAMethod

    commit = sys.argv[1] if len(sys.argv) > 1 else "unknown"
    config = NHAConfig.quick()
    for k, v in reference_settings().items():
        setattr(config, k, v)
    calls = []
    original = NHAMethod.losses

    def recording(self, *args, **kwargs):
        terms = original(self, *args, **kwargs)
        calls.append({k: float(v.detach()) for k, v in terms.items()})
        return terms

    NHAMethod.losses = recording
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        dataset = write_rendered_dataset(Path(tmp) / "data", use_tiny_head())
        metrics = engine.fit("nha", dataset, Path(tmp) / "run", config, log=lambda m: None)
    out = {"commit": commit, "settings": reference_settings(), "calls": calls, "val_psnr": metrics["val_psnr"]}
    (HERE / "nha_reference_losses.json").write_text(json.dumps(out))
    print(f"{len(calls)} energy evaluations, val PSNR {metrics['val_psnr']}")


if __name__ == "__main__":
    main()
