"""Checks of scene-description values: each either returns the value converted or raises :class:`SpecError`
naming the file and the field (``src: where: what was expected, what was found``)."""

from __future__ import annotations

__all__ = ["SpecError", "check_keys", "fail", "flat", "floats", "number", "positive", "rgba"]


class SpecError(ValueError):
    """A scene description is malformed; the message names the file and the field."""


def fail(src: str, where: str, msg: str) -> SpecError:
    return SpecError(f"{src}: {where}: {msg}")


def check_keys(d: dict, allowed, src: str, where: str) -> None:
    if not isinstance(d, dict):
        raise fail(src, where, f"expected an object, got {type(d).__name__}")
    extra = sorted(set(d) - set(allowed))
    if extra:
        raise fail(src, where, f"unknown keys {extra}; allowed {sorted(allowed)}")


def floats(v, n: int, src: str, where: str) -> tuple[float, ...]:
    if not isinstance(v, list | tuple) or len(v) != n or not all(isinstance(x, int | float) for x in v):
        raise fail(src, where, f"expected {n} numbers, got {v!r}")
    return tuple(float(x) for x in v)


def positive(v, src: str, where: str) -> float:
    if not isinstance(v, int | float) or not v > 0:
        raise fail(src, where, f"expected a positive number, got {v!r}")
    return float(v)


def rgba(v, src: str, where: str) -> tuple[float, float, float, float]:
    if isinstance(v, list | tuple) and len(v) == 3:
        v = [*v, 1.0]
    return floats(v, 4, src, where)  # type: ignore[return-value]


def flat(cls, d: dict, src: str, where: str, conv: dict):
    """Build a flat dataclass from ``d`` converting each present key with ``conv[key](value, src,
    where.key)``."""
    check_keys(d, conv, src, where)
    kw = {k: conv[k](v, src, f"{where}.{k}") for k, v in d.items()}
    return cls(**kw)


def number(v, src, where) -> float:
    if not isinstance(v, int | float):
        raise fail(src, where, f"expected a number, got {v!r}")
    return float(v)
