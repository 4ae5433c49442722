"""The avatar platform: NHA unchanged by the move onto the engine, self-contained run folders,
the scoring protocol, and a second (toy) method that plugs in without touching NHA."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from headforge.errors import HeadforgeError

sys.path.insert(0, str(Path(__file__).parent / "data"))
sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture
def tiny_head(monkeypatch):
    """``load_data("tiny-nha")`` gives the fixed tiny NHA head (tests/conftest.py)."""
    import headforge.head
    from conftest import tiny_nha_head_data

    data = tiny_nha_head_data()
    original = headforge.head.load_data
    monkeypatch.setattr(headforge.head, "load_data",
                        lambda name="open-head", *a, **k: data if name == data.name else original(name, *a, **k))
    return data


@pytest.fixture
def rendered(tmp_path, tiny_head):
    from conftest import write_rendered_dataset

    return write_rendered_dataset(tmp_path / "data", tiny_head)


def test_nha_on_the_engine_reproduces_the_old_trainers_losses(rendered, tmp_path, monkeypatch):
    """Every energy evaluation of a 50-iteration tiny run (training steps, the per-frame
    alignment, in-training validation and test-time fitting) equals the pre-platform trainer's,
    recorded by tests/data/make_nha_reference.py at commit 64909a8."""
    from make_nha_reference import reference_settings

    from headforge.avatars import engine
    from headforge.avatars.nha.config import NHAConfig
    from headforge.avatars.nha.method import NHAMethod

    reference = json.loads((Path(__file__).parent / "data" / "nha_reference_losses.json").read_text())
    config = NHAConfig.quick()
    for k, v in reference_settings().items():
        setattr(config, k, v)
    calls = []
    original = NHAMethod.losses

    def recording(self, *args, **kwargs):
        terms = original(self, *args, **kwargs)
        calls.append({k: float(v.detach()) for k, v in terms.items()})
        return terms

    monkeypatch.setattr(NHAMethod, "losses", recording)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        engine.fit("nha", rendered, tmp_path / "run", config, log=lambda m: None)
    finally:
        torch.set_num_threads(threads)
    assert len(calls) == len(reference["calls"])
    for i, (got, want) in enumerate(zip(calls, reference["calls"])):
        assert got.keys() == want.keys(), i
        for k in want:
            assert got[k] == pytest.approx(want[k], rel=1e-6, abs=1e-9), (i, k)
