"""The runtime renders with numba: importing dsg_gym and running DSGWorld-v0 never imports torch."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_env_runs_without_importing_torch():
    code = """
        import sys
        import gymnasium as gym
        import dsg_gym
        assert "torch" not in sys.modules, "import dsg_gym"
        env = gym.make("DSGWorld-v0", width=32, height=32, obs=("rgb", "mask", "depth", "poses"))
        obs, _ = env.reset(seed=0)
        for _ in range(3):
            obs, *_ = env.step(env.action_space.sample())
        env.close()
        assert obs["rgb"].shape == (32, 32, 3)
        print("torch" in sys.modules)
    """
    res = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "False", "DSGWorld-v0 imported torch"
