"""Test-session settings that must be in place before numba, torch or MuJoCo load."""

import os

# One pytest process runs training code (which would pick numba's OpenMP layer) and forks
# AsyncVectorEnv workers after rendering; GNU OpenMP aborts on such a fork, so the whole session
# uses the fork-safe workqueue layer.
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
os.environ.setdefault("MUJOCO_GL", "egl")
