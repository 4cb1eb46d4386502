"""The ``training_faults`` section of ``python -m benchmarks.stress``: non-finite gradients injected at random
steps of a single-state training must stop it with a clear error and the last good checkpoint kept, resuming
from it must give the world of a fault-free run, and truncated checkpoints must be refused."""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm


def _bar(total: int, desc: str, progress: bool):
    return tqdm(
        total=total, desc=desc, disable=not progress, dynamic_ncols=True, mininterval=1.0, leave=False
    )


def training_faults(steps: int, faults: int, progress: bool) -> dict:
    from _captures import tiny_capture

    from dsg_gym.world import encode_world
    from train_world.single_state.checkpoint import CheckpointError, load_checkpoint
    from train_world.single_state.data import load_training_data
    from train_world.single_state.presets import TrainConfig, get_preset
    from train_world.single_state.trainer import Trainer, TrainingDiverged

    every = max(2, steps // 6)
    cfg = TrainConfig(
        preset=get_preset("quick", iterations=steps, checkpoint_every=every), single_state=True, seed=5
    )
    rng = np.random.default_rng(0)
    candidates = [s for s in range(every + 1, steps + 1) if s % every]
    fault_steps = sorted(rng.choice(candidates, size=min(faults, len(candidates)), replace=False).tolist())
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        data = load_training_data(tiny_capture(tmp, views=8, test_views=1), cfg)
        t_data = time.perf_counter() - t0
        t0 = time.perf_counter()
        clean = Trainer(data, cfg, checkpoint=tmp / "clean.ckpt")
        clean.train(progress=False)
        t_clean = time.perf_counter() - t0
        want = encode_world(clean.world())

        t0 = time.perf_counter()
        ckpt = tmp / "faulty.ckpt"
        t = Trainer(data, cfg, checkpoint=ckpt)
        events, resumes = [], 0
        bar = _bar(steps, "training with faults", progress)
        for fs in fault_steps:
            t.train(progress=False, stop_after=fs - 1)
            blob = ckpt.read_bytes()
            name = ["means", "opacity_logits", "sh0", "features"][len(events) % 4]
            handle = getattr(t.field, name).register_hook(lambda g: torch.full_like(g, math.nan))
            try:
                t.train(progress=False)
                message = None
            except TrainingDiverged as e:
                message = str(e)
            handle.remove()
            intact = ckpt.read_bytes() == blob
            t = Trainer(data, cfg, checkpoint=ckpt)
            t.load_checkpoint()
            resumes += 1
            events.append({"step": fs, "parameter": name, "error": message, "checkpoint_intact": intact,
                           "resumed_at": t.step})  # fmt: skip
            bar.update(fs - bar.n)
        t.train(progress=False)
        bar.close()
        t_faulty = time.perf_counter() - t0
        same = encode_world(t.world()) == want

        blob = ckpt.read_bytes()
        (hlen,) = np.frombuffer(blob[:8], dtype="<u8")
        cuts = sorted(
            {0, 4, 8, 8 + int(hlen) // 2, 8 + int(hlen), len(blob) // 3, len(blob) // 2, len(blob) - 1}
        )
        refused = 0
        for cut in cuts:
            bad = tmp / "cut.ckpt"
            bad.write_bytes(blob[:cut])
            try:
                load_checkpoint(bad)
            except CheckpointError:
                refused += 1
    all_stopped = all(e["error"] and "non-finite" in e["error"] and e["checkpoint_intact"] for e in events)
    return {
        "steps": steps,
        "checkpoint_every": every,
        "fault_steps": fault_steps,
        "events": events,
        "resumes": resumes,
        "world_equals_fault_free_run": same,
        "truncated_checkpoints_refused": f"{refused}/{len(cuts)}",
        "seconds": {"capture_and_load": t_data, "fault_free_run": t_clean, "run_with_faults": t_faulty},
        "passed": bool(all_stopped and same and refused == len(cuts)),
    }


# ------------------------------------------------------------------------------------------------ main
