"""Which views of a capture train a two-state world: captures with two training states and the views held
out of them for evaluation."""

from __future__ import annotations

from pathlib import Path

__all__ = ["HOLDOUT_WITHOUT_TEST_STATES", "default_holdout_every", "has_two_training_states"]

#: views held out of each training state (every n-th) when the capture has no test states to evaluate on
HOLDOUT_WITHOUT_TEST_STATES = 8


def has_two_training_states(path: str | Path) -> bool:
    """True for a capture folder whose ``scene.json`` lists ``state1`` and ``state2`` as training states."""
    p = Path(path)
    if not (p.is_dir() and (p / "scene.json").is_file()):
        return False
    try:
        from train_world.capture import load_capture

        cap = load_capture(p, states=[], load_depth=False)
    except ValueError:  # CaptureError: not a readable capture
        return False
    return all(cap.splits.get(s) == "train" for s in ("state1", "state2"))


def default_holdout_every(path: str | Path) -> int:
    """Views held out of each training state by default: none (0) when the capture has test states, whose
    cameras are the evaluation (``dsg-eval``), so every captured view trains; else every
    :data:`HOLDOUT_WITHOUT_TEST_STATES`-th view, to have held-out views to evaluate on."""
    from train_world.capture import load_capture

    cap = load_capture(Path(path), states=[], load_depth=False)  # metadata only
    return 0 if any(split == "test" for split in cap.splits.values()) else HOLDOUT_WITHOUT_TEST_STATES
