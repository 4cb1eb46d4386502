"""The bundled data: scene descriptions (``scenes/*.json``) and world files (``worlds/*.dsgworld``).

The repository keeps them in its top-level ``assets/`` folder; a wheel carries the same files as package data
``dsg_gym/_assets/`` (``pyproject.toml`` maps that package onto ``assets/``). :func:`assets_dir` returns the
first of these that exists: the installed package data (found with :mod:`importlib.resources`), else the
``assets/`` folder of the source checkout this module lies in (an editable install, or ``PYTHONPATH=.``).

Light to import (standard library only), so both ``dsg_gym`` and ``train_world`` use it::

    from dsg_gym.assets import scene_names, world_path

    world_path("two_blocks_dsg")   # .../worlds/two_blocks_dsg.dsgworld
    scene_names()                  # ['five_small', 'floor_rug', ...]
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = [
    "AssetsNotFoundError",
    "WORLD_SUFFIX",
    "WORLD_SUFFIXES",
    "assets_dir",
    "scene_names",
    "scene_path",
    "scenes_dir",
    "world_names",
    "world_path",
    "worlds_dir",
]

#: the extension of world files (readers accept any name)
WORLD_SUFFIX = ".dsgworld"
#: what a scan of a folder for world files takes: ``.dsgw`` is the extension of older files
WORLD_SUFFIXES = (WORLD_SUFFIX, ".dsgw")
#: the package data folder inside an installed ``dsg_gym``
_PACKAGE_DATA = "_assets"


class AssetsNotFoundError(FileNotFoundError):
    """Neither the installed package data nor a source checkout's ``assets/`` folder is there."""


def _candidates() -> list[Path]:
    """Where the assets may be: the installed package data, then the source checkout's ``assets/``."""
    packaged = resources.files("dsg_gym").joinpath(_PACKAGE_DATA)
    if not isinstance(packaged, Path):  # not on the file system (a zip import): no paths to hand out
        packaged = Path(__file__).resolve().parent / _PACKAGE_DATA
    out = [packaged]
    checkout = Path(__file__).resolve().parents[1]
    if (checkout / "pyproject.toml").is_file():  # not site-packages, where another package may own "assets"
        out.append(checkout / "assets")
    return out


def _find() -> Path | None:
    for c in _candidates():
        if (c / "scenes").is_dir() or (c / "worlds").is_dir():
            return c
    return None


def _root() -> Path:
    """The assets folder, or where the installed one should be when there is none (errors then name it)."""
    return _find() or _candidates()[0]


def assets_dir() -> Path:
    """The folder holding ``scenes/`` and ``worlds/``; raises :class:`AssetsNotFoundError` (one line, naming
    where it looked) when there is none."""
    found = _find()
    if found is None:
        raise AssetsNotFoundError(
            "dsg-gym's bundled assets (scenes/, worlds/) are missing: looked in "
            + " and ".join(str(c) for c in _candidates())
            + "; reinstall dsg-gym (its wheel carries them as dsg_gym/_assets)"
        )
    return found


def scenes_dir() -> Path:
    """The folder of the default scene descriptions (``<name>.json``). Does not raise: with no assets
    installed it is a folder that does not exist (:func:`scene_names` is then empty)."""
    return _root() / "scenes"


def worlds_dir() -> Path:
    """The folder of the bundled world files (``<name>.dsgworld``); never raises, as :func:`scenes_dir`."""
    return _root() / "worlds"


def scene_names() -> list[str]:
    """Names of the default scenes, sorted (empty when the folder holds none)."""
    d = scenes_dir()
    return sorted(p.stem for p in d.glob("*.json")) if d.is_dir() else []


def scene_path(name: str) -> Path:
    """The description file of default scene ``name`` (it may not exist: check before reading)."""
    return scenes_dir() / f"{name}.json"


def world_names() -> list[str]:
    """Names (without extension) of the bundled worlds, sorted."""
    d = worlds_dir()
    if not d.is_dir():
        return []
    return sorted({p.stem for p in d.iterdir() if p.suffix in WORLD_SUFFIXES and p.is_file()})


def world_path(name: str) -> Path:
    """The bundled world file ``name`` (with or without its extension; ``NAME.dsgworld``, or an existing
    ``NAME.dsgw``). It may not exist: the loader's error then names the path."""
    d = worlds_dir()
    if name.endswith(WORLD_SUFFIXES):
        return d / name
    old = d / f"{name}.dsgw"
    new = d / f"{name}{WORLD_SUFFIX}"
    return old if old.is_file() and not new.is_file() else new
