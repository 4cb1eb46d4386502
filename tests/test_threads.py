"""The runtime renderer under numba's OpenMP layer: parallel in the main process, single-threaded (same
images) in vector-env workers, including workers forked after the parent rendered with OpenMP threads
(GNU OpenMP does not survive fork; numba would terminate such a worker at its first parallel kernel)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent(
    """
    import multiprocessing as mp
    import numba
    import numpy as np
    import gymnasium as gym
    import dsg_gym
    from dsg_gym.splat.threads import parallel_allowed

    def child(q):
        q.put((parallel_allowed(), parallel_allowed(True), parallel_allowed(False)))

    if __name__ == "__main__":
        assert parallel_allowed() and parallel_allowed(True) and not parallel_allowed(False)
        env = gym.make("DSGWorld-v0", width=48, height=32, obs=("rgb", "mask"))
        obs, _ = env.reset(seed=3)
        assert numba.threading_layer() == "omp", numba.threading_layer()
        a = np.zeros(env.action_space.shape, np.float32)
        a[:4] = [0.5, -0.3, 0.0, 0.4]
        obs1 = env.step(a)[0]
        # a worker forked after OpenMP threads started: no threads, even when asked for
        ctx = mp.get_context("fork")
        q = ctx.Queue()
        p = ctx.Process(target=child, args=(q,))
        p.start()
        got = q.get(timeout=60)
        p.join()
        assert got == (False, False, False), got
        envs = gym.make_vec("DSGWorld-v0", num_envs=2, vectorization_mode="async",
                            vector_kwargs={"shared_memory": True, "context": "fork"},
                            width=48, height=32, obs=("rgb", "mask"))
        vobs, _ = envs.reset(seed=[3, 3])
        for key in ("rgb", "mask"):
            assert np.array_equal(vobs[key][0], obs[key]) and np.array_equal(vobs[key][1], obs[key]), key
        vobs = envs.step(np.stack([a, a]))[0]
        for key in ("rgb", "mask"):
            assert np.array_equal(vobs[key][0], obs1[key]), key
        envs.close()
        print("ok")
    """
)


def test_vector_env_workers_forked_after_openmp_render_the_same_images(tmp_path):
    script = tmp_path / "fork_after_omp.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "NUMBA_THREADING_LAYER": "omp", "MUJOCO_GL": "egl"}
    r = subprocess.run(
        [sys.executable, str(script)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stdout[-2000:] + r.stderr[-3000:]
