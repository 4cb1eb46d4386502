"""Captures on disk: the layout (:mod:`.format`), camera conventions (:mod:`.cameras`) and loading
(:mod:`.loader`). See docs/captures.md."""

from train_world.capture.loader import (
    Capture,
    CaptureError,
    ObjectInfo,
    Views,
    load_blender,
    load_capture,
    load_views,
)

__all__ = ["Capture", "CaptureError", "ObjectInfo", "Views", "load_blender", "load_capture", "load_views"]
