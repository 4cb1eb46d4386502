"""Which views of a capture train a two-state world: captures with two training states, the views held out of
them for evaluation, the names of a state's views, and whether the capture's object motions are estimates."""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "ESTIMATING_GENERATORS",
    "HOLDOUT_WITHOUT_TEST_STATES",
    "default_holdout_every",
    "has_two_training_states",
    "motions_estimated",
    "view_names",
]

#: capture generators (``scene.json``'s ``generator.name``) whose object motions are estimates, not known
ESTIMATING_GENERATORS = ("dsg-capture",)

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


def motions_estimated(path: str | Path) -> bool:
    """True when the capture's object motions between its states are estimates: it was made by a generator of
    :data:`ESTIMATING_GENERATORS` (``dsg-capture``, from photos). Synthetic captures know them exactly. False
    for a folder without ``scene.json`` (loading the capture for training names that error)."""
    from train_world.capture import load_capture

    if not (Path(path) / "scene.json").is_file():
        return False
    gen = load_capture(Path(path), states=[], load_depth=False).metadata.get("generator")
    return isinstance(gen, dict) and gen.get("name") in ESTIMATING_GENERATORS


def view_names(path: str | Path, state: str) -> list[str]:
    """The names (image file stems) of every view of ``state`` in the capture, in its ``transforms.json``
    order (the order of the cameras a world stores); no image is read."""
    from train_world.capture.files import CaptureError, read_json

    tj = Path(path) / state / "transforms.json"
    doc = read_json(tj)
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, list) or not all(isinstance(f, dict) and "file_path" in f for f in frames):
        raise CaptureError(f"{tj}: expected a 'frames' list whose entries have a 'file_path'")
    return [Path(str(f["file_path"])).stem for f in frames]
