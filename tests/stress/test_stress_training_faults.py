"""Single-state training under injected faults: a NaN gradient, corrupted checkpoints and an
interrupted checkpoint write. Each stops with a clear error and leaves the last good checkpoint and world
file intact and loadable; training resumes from them. Tiny runs: a 32x32 capture with 8 views per state and
the ``quick`` preset cut to 12 steps (checkpoints every 4).
"""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
import torch
from _captures import tiny_capture

from dsg_gym.world import load_world
from train_world.capture import format as data_format
from train_world.cli import train as cli
from train_world.single_state.checkpoint import CheckpointError, load_checkpoint
from train_world.single_state.data import load_training_data
from train_world.single_state.presets import TrainConfig, get_preset
from train_world.single_state.trainer import Trainer, TrainingDiverged

STEPS, EVERY = 12, 4


def _config() -> TrainConfig:
    return TrainConfig(
        preset=get_preset("quick", iterations=STEPS, checkpoint_every=EVERY), single_state=True, seed=5
    )


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return tiny_capture(tmp_path_factory.mktemp("cap"), views=8, test_views=1)


@pytest.fixture(scope="module")
def data(capture):
    return load_training_data(capture, _config())


@pytest.fixture(scope="module")
def good_run(data, tmp_path_factory):
    """A trainer stopped after its first checkpoint (step 4), with its checkpoint and world file."""
    folder = tmp_path_factory.mktemp("good")
    t = Trainer(data, _config(), checkpoint=folder / "run.ckpt")
    t.train(progress=False, stop_after=EVERY)
    world = t.write_world(folder / "run.dsgworld")
    return t, folder / "run.ckpt", world


def _params(t: Trainer) -> dict[str, torch.Tensor]:
    out = {k: v.detach().clone() for k, v in t.field.params().items()}
    out.update({f"classifier.{k}": v.detach().clone() for k, v in t.classifier.named_parameters()})
    return out


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k, v in a.items():
        assert torch.equal(v, b[k]), k


def _poison_once(grad: torch.Tensor) -> torch.Tensor:
    """A gradient hook: one NaN entry, the rest untouched (the loss itself stays finite)."""
    g = grad.clone()
    g.view(-1)[0] = float("nan")
    return g


@pytest.mark.parametrize("target", ["means", "classifier.weight"])
def test_nan_gradient_stops_cleanly_and_the_last_good_state_survives(data, tmp_path, target):
    ckpt, world = tmp_path / "t.ckpt", tmp_path / "t.dsgworld"
    t = Trainer(data, _config(), checkpoint=ckpt)
    t.train(progress=False, stop_after=EVERY)
    t.write_world(world)
    good_ckpt, good_world, before = ckpt.read_bytes(), world.read_bytes(), _params(t)
    param = t.classifier.weight if target == "classifier.weight" else getattr(t.field, target)
    handle = param.register_hook(_poison_once)
    with pytest.raises(TrainingDiverged, match=rf"gradient of {target} became non-finite at step 5.*step 4"):
        t.train(progress=False)
    handle.remove()
    # the failed step changed nothing: in memory, on disk
    assert t.step == EVERY
    _assert_same(_params(t), before)
    assert ckpt.read_bytes() == good_ckpt and world.read_bytes() == good_world
    assert load_world(world).metadata["iterations"] == EVERY
    # the surviving checkpoint resumes to the end with finite parameters and a loadable world
    resumed = Trainer(data, _config(), checkpoint=ckpt)
    resumed.load_checkpoint()
    _assert_same(_params(resumed), before)
    resumed.train(progress=False)
    assert resumed.step == STEPS
    assert all(bool(torch.isfinite(v).all()) for v in _params(resumed).values())
    assert load_world(resumed.write_world(tmp_path / "done.dsgworld")).metadata["iterations"] == STEPS


def _cuts(blob: bytes) -> list[int]:
    (hlen,) = struct.unpack("<Q", blob[:8])
    return [0, 5, 8, 8 + hlen // 2, 8 + hlen, 8 + hlen + 1, len(blob) // 2, len(blob) - 1]


def test_truncated_checkpoints_are_refused_and_the_good_one_still_loads(data, good_run, tmp_path):
    trained, ckpt, _ = good_run
    blob = ckpt.read_bytes()
    fresh = Trainer(data, _config(), checkpoint=tmp_path / "fresh.ckpt")
    untouched = _params(fresh)
    for cut in _cuts(blob):
        bad = tmp_path / f"cut{cut}.ckpt"
        bad.write_bytes(blob[:cut])
        with pytest.raises(CheckpointError, match=rf"{bad.name}: .*(truncated|corrupt)"):
            load_checkpoint(bad)
        with pytest.raises(CheckpointError):
            fresh.load_checkpoint(bad)
        assert fresh.step == 0  # a refused checkpoint leaves the trainer as it was
        _assert_same(_params(fresh), untouched)
    garbled = bytearray(blob)
    garbled[8:16] = b"\xff" * 8  # inside the JSON header
    (tmp_path / "garbled.ckpt").write_bytes(bytes(garbled))
    with pytest.raises(CheckpointError, match="not a dsg-train checkpoint"):
        load_checkpoint(tmp_path / "garbled.ckpt")
    # one flipped bit in the tensor data (the checkpoint's SHA-256 catches it)
    (hlen,) = struct.unpack("<Q", blob[:8])
    for at in (8 + hlen, 8 + hlen + (len(blob) - 8 - hlen) // 2, len(blob) - 1):
        flipped = bytearray(blob)
        flipped[at] ^= 0x04
        (tmp_path / "flipped.ckpt").write_bytes(bytes(flipped))
        with pytest.raises(CheckpointError, match="does not match its SHA-256"):
            fresh.load_checkpoint(tmp_path / "flipped.ckpt")
        assert fresh.step == 0
    assert ckpt.read_bytes() == blob
    fresh.load_checkpoint(ckpt)
    assert fresh.step == EVERY
    _assert_same(_params(fresh), _params(trained))


def test_cli_resume_from_a_truncated_checkpoint_fails_with_a_clear_error(capture, good_run, tmp_path, capsys):
    _, ckpt, _ = good_run
    bad = tmp_path / "w.dsgworld.ckpt"
    bad.write_bytes(ckpt.read_bytes()[:1000])
    argv = [str(capture), "--out", str(tmp_path / "w.dsgworld"), "--preset", "quick", "--iterations", str(STEPS),
            "--single-state", "--seed", "5", "--resume", "--quiet"]  # fmt: skip
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "w.dsgworld.ckpt" in err and "truncated" in err
    assert not (tmp_path / "w.dsgworld").exists()  # no world from a failed run


def test_interrupted_checkpoint_write_keeps_the_previous_checkpoint(good_run, monkeypatch):
    trained, ckpt, world = good_run
    blob = ckpt.read_bytes()

    def no_rename(src, dst):
        raise OSError("disk full (injected)")

    monkeypatch.setattr(data_format.os, "replace", no_rename)
    with pytest.raises(OSError, match="injected"):
        trained.save_checkpoint()
    with pytest.raises(OSError, match="injected"):
        trained.write_world(world)
    monkeypatch.undo()
    assert ckpt.read_bytes() == blob
    assert sorted(p.name for p in ckpt.parent.iterdir()) == ["run.ckpt", "run.dsgworld"]  # no temp files left
    assert load_checkpoint(ckpt)[1]["step"] == EVERY and load_world(world).metadata["iterations"] == EVERY
