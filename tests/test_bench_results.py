"""benchmarks._results: the default output path of every benchmark, by benchmark, date and commit, and the
machine that every result records."""

from __future__ import annotations

import datetime
import json
import re
import subprocess
from pathlib import Path

import pytest

from benchmarks._results import RESULTS, default_out, machine_info, short_commit, write_result

REPO = Path(__file__).resolve().parents[1]


def test_default_out_names_benchmark_date_and_commit(tmp_path):
    day = datetime.date(2026, 11, 24)
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    commit = head.stdout.strip() if head.returncode == 0 else "nocommit"
    assert short_commit() == commit
    assert default_out("env_step", date=day) == RESULTS / "env_step" / f"2026-11-24-{commit}.json"
    assert RESULTS == REPO / "benchmarks" / "results"
    assert default_out("pareto", "", date=day, root=tmp_path) == tmp_path / "pareto" / f"2026-11-24-{commit}"
    assert not (tmp_path / "pareto").exists()  # nothing is created
    today = default_out("collect")
    assert (
        re.fullmatch(r"\d{4}-\d{2}-\d{2}-[0-9a-z]+\.json", today.name) and today.parent == RESULTS / "collect"
    )
    assert datetime.date.fromisoformat(today.name[:10]) == datetime.date.today()
    for bad in ("", "a/b", ".hidden"):
        with pytest.raises(ValueError, match="plain name"):
            default_out(bad)


def test_outside_git_the_commit_is_nocommit(tmp_path, monkeypatch):
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))  # git must not find a repo above
    monkeypatch.delenv("GIT_DIR", raising=False)
    assert short_commit(tmp_path) == "nocommit"
    p = default_out("render", date=datetime.date(2026, 1, 2), root=tmp_path, cwd=tmp_path)
    assert p == tmp_path / "render" / "2026-01-02-nocommit.json"
    monkeypatch.setenv("PATH", str(tmp_path))  # no git at all
    assert short_commit() == "nocommit"


def test_every_benchmark_with_an_out_option_defaults_to_it():
    """Each script taking ``--out`` fills it from :func:`default_out` when it is not given."""
    out_option = re.compile(r'add_argument\(\s*"--out"')
    scripts = [p for p in sorted((REPO / "benchmarks").glob("*.py")) if out_option.search(p.read_text())]
    assert {"collect", "env_step", "pareto", "render", "stress", "train_step"} <= {p.stem for p in scripts}
    for path in scripts:
        text = path.read_text()
        assert re.search(rf'default_out\(\s*"{path.stem}"', text), path.name
        assert not re.search(r'add_argument\(\s*"--out"[^)]*required=True', text), path.name


def test_results_say_which_machine_measured_them(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: X\nmodel name\t: Test CPU @ 1.0GHz\n\nprocessor\t: 1\n")
    m = machine_info(info)
    assert m["cpu"] == "Test CPU @ 1.0GHz" and m["cpus"] >= 1 and m["python"].count(".") == 2
    assert machine_info(tmp_path / "missing")["cpu"]  # no cpuinfo: the platform's name or "unknown"
    write_result(tmp_path / "a" / "r.json", {"x": 1})
    assert json.loads((tmp_path / "a" / "r.json").read_text())["machine"]["cpus"] == m["cpus"]
    mine = {"x": 1, "machine": {"cpus": 99}}
    write_result(tmp_path / "b.json", mine)
    assert json.loads((tmp_path / "b.json").read_text())["machine"] == {"cpus": 99}
    assert mine == {"x": 1, "machine": {"cpus": 99}}
