"""The package layout: no import circles between modules, the runtime never imports the training package,
argument parsing only in CLI modules, and no module grows past the size one job needs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dsg_gym", "train_world", "benchmarks")
MAX_LINES = 520


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = path
    return mods


def _imports(name: str, path: Path, mods: dict[str, Path]) -> set[str]:
    """Modules of ours that ``name`` imports (at any depth of its code, lazy imports included)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")[: len(name.split(".")) - node.level + (path.name == "__init__.py")]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            cands = [target] + [f"{target}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            cands = [a.name for a in node.names]
        else:
            continue
        out.update(c for c in cands if c in mods and c != name)
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    mods = _modules()
    # a package's __init__ importing its own submodules is how packages re-export: not a circle
    return {
        m: {t for t in _imports(m, p, mods) if not (p.name == "__init__.py" and t.startswith(m + "."))}
        for m, p in mods.items()
    }


def test_no_import_circles(graph):
    seen: dict[str, int] = {}  # 1: on the stack, 2: done
    cycles = []

    def visit(m: str, stack: list[str]) -> None:
        seen[m] = 1
        for t in sorted(graph[m]):
            if seen.get(t) == 1:
                cycles.append(stack[stack.index(t) :] + [t])
            elif t not in seen:
                visit(t, stack + [t])
        seen[m] = 2

    for m in sorted(graph):
        if m not in seen:
            visit(m, [m])
    assert not cycles, f"import circles: {cycles}"


def test_runtime_never_imports_training_or_benchmarks(graph):
    bad = {
        m: sorted(t for t in ts if not t.startswith("dsg_gym"))
        for m, ts in graph.items()
        if m.startswith("dsg_gym")
    }
    assert not {m: ts for m, ts in bad.items() if ts}


def test_library_never_imports_benchmarks_or_cli_modules(graph):
    def is_cli(mod: str) -> bool:
        return ".cli." in f".{mod}."

    bad = {
        m: sorted(t for t in ts if t.startswith("benchmarks") or is_cli(t))
        for m, ts in graph.items()
        if not m.startswith("benchmarks") and not is_cli(m)
    }
    assert not {m: ts for m, ts in bad.items() if ts}


def test_argparse_only_in_cli_modules_and_benchmarks():
    offenders = []
    for name, path in _modules().items():
        if name.startswith("benchmarks") or ".cli" in name:
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                if "argparse" in names:
                    offenders.append(name)
    assert not offenders, f"argument parsing outside */cli/: {offenders}"


def test_no_module_past_its_size():
    long = {n: len(p.read_text().splitlines()) for n, p in _modules().items()}
    assert not {n: k for n, k in long.items() if k > MAX_LINES}
