#!/usr/bin/env bash
# Wheel smoke test: does dsg-gym install and run like a package, away from this checkout?
#   1. builds the wheel (pip wheel --no-deps) from a copy of the working tree (tracked + untracked, not ignored)
#   2. creates a fresh venv outside the checkout, installs torch==2.13.0 (the local CPU wheel) and then the wheel
#      (its other dependencies come from PyPI)
#   3. from a folder outside the checkout: `dsg-synth --list` must list the scenes of assets/scenes/, and
#      gym.make("DSGWorld-v0") on the bundled world, reset and 5 steps, with `import dsg_gym` not importing torch
# Usage: bash .ci/wheel_smoke.sh        (PYTHON=python3.11 to pick the interpreter; KEEP=1 keeps the temp folder)
set -euo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
PYTHON="${PYTHON:-python3}"
WORK="$(mktemp -d "${TMPDIR:-/tmp}/dsg-wheel-smoke.XXXXXX")"
if [ -z "${KEEP:-}" ]; then trap 'rm -rf "$WORK"' EXIT; fi
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYTHONNOUSERSITE=1 PIP_DISABLE_PIP_VERSION_CHECK=1
unset PYTHONPATH PYTHONHOME VIRTUAL_ENV
t0=$SECONDS
say() { echo "wheel-smoke: [$((SECONDS - t0)) s] $*"; }

# 1. the wheel, built from a copy so that the checkout gets no build/ or *.egg-info
mkdir -p "$WORK/src" "$WORK/dist" "$WORK/run"
if git -C "$REPO" rev-parse --is-inside-work-tree >/dev/null 2>&1; then
    (cd "$REPO" && git ls-files -z -co --exclude-standard | "$PYTHON" -c '
import os, shutil, sys
dst = sys.argv[1]
for f in sys.stdin.buffer.read().decode().split("\0"):
    if f and os.path.isfile(f):  # tracked files deleted in the work tree are left out
        os.makedirs(os.path.join(dst, os.path.dirname(f)), exist_ok=True)
        shutil.copy2(f, os.path.join(dst, f))
' "$WORK/src")
else
    cp -a "$REPO/." "$WORK/src/"
fi
"$PYTHON" -m venv "$WORK/venv"
VPY="$WORK/venv/bin/python"
"$VPY" -m pip install -q --upgrade pip
"$VPY" -m pip wheel -q --no-deps "$WORK/src" -w "$WORK/dist"
WHEEL="$(ls "$WORK"/dist/dsg_gym-*.whl)"
say "built $(basename "$WHEEL") ($(du -h "$WHEEL" | cut -f1))"

# 2. torch first (the pinned CPU wheel: pip never resolves torch itself), then the wheel
"$VPY" -m pip install -q torch==2.13.0
"$VPY" -m pip install -q "$WHEEL"
torch_version="$("$VPY" -c 'import importlib.metadata as m; print(m.version("torch"))')"
case "$torch_version" in
    2.13.0*) ;;
    *) echo "wheel-smoke: FAILED: installing the wheel changed torch to $torch_version" >&2; exit 1 ;;
esac
say "installed into a fresh venv ($(du -sh "$WORK/venv" | cut -f1), torch $torch_version)"

# 3. run it from outside the checkout
cd "$WORK/run"
expected="$(cd "$REPO/assets/scenes" && ls -- *.json | sed 's/\.json$//' | sort)"
listed="$("$WORK/venv/bin/dsg-synth" --list | awk '{print $1}' | sort)"
if [ -z "$listed" ] || [ "$listed" != "$expected" ]; then
    echo "wheel-smoke: FAILED: dsg-synth --list printed [$(echo $listed)], expected [$(echo $expected)]" >&2
    exit 1
fi
say "dsg-synth --list: $(echo "$listed" | wc -l) scenes: $(echo $listed)"
# without its scene descriptions the installed package says so in one line and fails
scenes="$("$VPY" -c 'from dsg_gym.assets import scenes_dir; print(scenes_dir())')"
mv "$scenes" "$scenes.away"
rc=0
"$WORK/venv/bin/dsg-synth" --list >"$WORK/list.out" 2>"$WORK/list.err" || rc=$?
mv "$scenes.away" "$scenes"
if [ "$rc" = 0 ] || [ -s "$WORK/list.out" ] || [ "$(wc -l <"$WORK/list.err")" != 1 ]; then
    echo "wheel-smoke: FAILED: dsg-synth --list without scenes: status $rc, stdout/stderr:" >&2
    cat "$WORK/list.out" "$WORK/list.err" >&2
    exit 1
fi
say "dsg-synth --list without scenes: status $rc, $(cat "$WORK/list.err")"

"$VPY" - "$REPO" <<'EOF'
import sys
import traceback
from pathlib import Path

repo = Path(sys.argv[1]).resolve()
chains = {}


class _TorchSpy:
    """Remembers which of our frames imported torch first (the chain to report)."""

    def find_spec(self, name, path=None, target=None):
        if name == "torch" and "torch" not in chains:
            stack = traceback.extract_stack()[:-1]
            chains["torch"] = [f"{f.filename}:{f.lineno} {f.line}" for f in stack if "importlib" not in f.filename]
        return None


sys.meta_path.insert(0, _TorchSpy())


def torch_check(after: str) -> None:
    if "torch" in sys.modules:
        sys.exit(f"wheel-smoke: FAILED: {after} imported torch, through:\n  " + "\n  ".join(chains.get("torch", [])))


import gymnasium as gym  # noqa: E402

import dsg_gym  # noqa: E402

here = Path(dsg_gym.__file__).resolve()
assert repo not in here.parents, f"dsg_gym was imported from the checkout ({here}), not from the wheel"
torch_check("import dsg_gym")
env = gym.make("DSGWorld-v0", width=32, height=32)
obs, info = env.reset(seed=0)
for _ in range(5):
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
env.close()
assert obs["rgb"].shape == (32, 32, 3), obs["rgb"].shape
torch_check("DSGWorld-v0 (make, reset, 5 steps)")
print(f"wheel-smoke: DSGWorld-v0 from {here.parent}: reset + 5 steps, rgb {obs['rgb'].shape}, torch not imported")
EOF
say "OK"
