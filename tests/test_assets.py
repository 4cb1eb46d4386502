"""dsg_gym.assets: the bundled scenes and worlds are found in a source checkout and in an installed wheel
(package data ``dsg_gym/_assets``); pyproject.toml ships all of them. The wheel itself is built and installed
in a fresh venv by ``.ci/wheel_smoke.sh`` (CI, after ``make test``)."""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

import pytest

from dsg_gym import assets

ROOT = Path(__file__).resolve().parents[1]
SCENES = [
    "five_small",
    "floor_rug",
    "four_mixed",
    "six_clutter",
    "textured_meshes",
    "three_primitives",
    "two_blocks",
]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _fake_assets(root: Path, scenes=("a",), worlds=("w.dsgworld",)) -> Path:
    (root / "scenes").mkdir(parents=True)
    (root / "worlds").mkdir()
    for s in scenes:
        (root / "scenes" / f"{s}.json").write_text("{}")
    for w in worlds:
        (root / "worlds" / w).write_bytes(b"x")
    return root


def test_bundled_scenes_and_worlds_are_found():
    from dsg_gym.envs.dsg_world import DEFAULT_WORLD, GEOMETRY_WORLD

    assert assets.scene_names() == SCENES
    assert all(assets.scene_path(s).is_file() for s in SCENES)
    assert assets.world_names() == ["default_geom", "two_blocks_dsg"]
    assert DEFAULT_WORLD == assets.world_path("two_blocks_dsg")
    assert DEFAULT_WORLD == assets.world_path("two_blocks_dsg.dsgworld")
    assert DEFAULT_WORLD.is_file() and GEOMETRY_WORLD.is_file()
    # from the checkout (editable install) they are the repository's assets/, the one copy there is
    assert assets.assets_dir().resolve() == (ROOT / "assets").resolve()


def test_installed_package_data_comes_first(monkeypatch, tmp_path):
    """In a wheel the files are dsg_gym/_assets/ inside the package, found through importlib.resources."""
    _fake_assets(tmp_path / "dsg_gym" / "_assets", scenes=("only_here",))
    monkeypatch.setattr(assets.resources, "files", lambda pkg: tmp_path / pkg)
    assert assets.assets_dir() == tmp_path / "dsg_gym" / "_assets"
    assert assets.scene_names() == ["only_here"]
    assert assets.world_path("w") == tmp_path / "dsg_gym" / "_assets" / "worlds" / "w.dsgworld"


def test_missing_assets_raise_one_line_naming_where_it_looked(monkeypatch, tmp_path):
    monkeypatch.setattr(assets, "_candidates", lambda: [tmp_path / "pkg", tmp_path / "repo"])
    with pytest.raises(assets.AssetsNotFoundError, match="reinstall dsg-gym") as e:
        assets.assets_dir()
    msg = str(e.value)
    assert "\n" not in msg and str(tmp_path / "pkg") in msg and str(tmp_path / "repo") in msg
    # the path helpers do not raise (importing the env must not fail); the loader names the missing file
    assert assets.scene_names() == [] and assets.world_names() == []
    assert assets.world_path("two_blocks_dsg") == tmp_path / "pkg" / "worlds" / "two_blocks_dsg.dsgworld"


def test_world_files_of_the_old_extension_are_found(monkeypatch, tmp_path):
    root = _fake_assets(tmp_path, worlds=("new.dsgworld", "old.dsgw", "both.dsgworld", "both.dsgw", "x.txt"))
    monkeypatch.setattr(assets, "_candidates", lambda: [root])
    assert assets.world_names() == ["both", "new", "old"]
    assert assets.world_path("old") == root / "worlds" / "old.dsgw"
    assert assets.world_path("both") == root / "worlds" / "both.dsgworld"
    assert assets.world_path("absent") == root / "worlds" / "absent.dsgworld"
    assert assets.world_path("old.dsgw") == root / "worlds" / "old.dsgw"


def test_dsg_synth_list_without_scenes_fails_with_one_line(monkeypatch, tmp_path, capsys):
    from train_world.cli import synth as synth_cli
    from train_world.synth import spec

    monkeypatch.setattr(assets, "_candidates", lambda: [tmp_path / "nowhere"])
    with pytest.raises(spec.SpecError, match="no default scene descriptions"):
        spec.default_scene_names()
    assert synth_cli.main(["--list"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and err.startswith("dsg-synth: error: no default scene")
    assert synth_cli.main(["--scene", "all", "--out", str(tmp_path / "out")]) == 2
    assert "no default scene descriptions" in capsys.readouterr().err


def test_pyproject_lists_every_package_and_ships_every_asset():
    st = PYPROJECT["tool"]["setuptools"]
    on_disk = {
        ".".join(p.parent.relative_to(ROOT).parts)
        for pkg in ("dsg_gym", "train_world")
        for p in (ROOT / pkg).rglob("__init__.py")
        if "__pycache__" not in p.parts
    }
    folders = [d.name for d in (ROOT / "assets").iterdir() if d.is_dir()]
    asset_pkgs = {"dsg_gym._assets"} | {f"dsg_gym._assets.{d}" for d in folders}
    assert set(st["packages"]) == on_disk | asset_pkgs, "add the package to [tool.setuptools] packages"
    assert st["package-dir"] == {"dsg_gym._assets": "assets"}
    data = st["package-data"]
    for f in (ROOT / "assets").rglob("*"):
        if f.is_file():
            pkg = "dsg_gym._assets." + f.parent.name
            assert any(f.match(g) for g in data.get(pkg, [])), f"{f} would not be in the wheel"
    assert "py.typed" in data["dsg_gym"] and "py.typed" in data["train_world"]
    assert (ROOT / "dsg_gym" / "py.typed").is_file() and (ROOT / "train_world" / "py.typed").is_file()
    assert PYPROJECT["project"]["license-files"] == ["LICENSE"] and (ROOT / "LICENSE").is_file()


@pytest.mark.parametrize("script", sorted(PYPROJECT["project"]["scripts"]))
def test_console_scripts_point_at_a_main(script):
    module, func = PYPROJECT["project"]["scripts"][script].split(":")
    assert callable(getattr(importlib.import_module(module), func))
