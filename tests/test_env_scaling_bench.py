"""benchmarks.env_scaling's breakdown: where an env step's time goes, for one env and the vector env."""

from __future__ import annotations

import json

from benchmarks.env_scaling import main
from dsg_gym.envs.dsg_world import DSGWorldEnv
from dsg_gym.envs.dsg_world_vector import DSGWorldVectorEnv


def test_breakdown_splits_the_step_and_leaves_the_env_classes_alone(tmp_path):
    classes = (DSGWorldEnv._transition, DSGWorldEnv._observe, DSGWorldVectorEnv._observe)
    out = tmp_path / "b.json"
    assert main(["--out", str(out), "--sections", "breakdown", "--steps", "32", "--repeats", "2"]) == 0
    r = json.loads(out.read_text())["breakdown"]
    for name in ("one_env_same_episodes", "vector16"):
        s = r[name]
        assert len(s["runs"]) == 2
        for run in s["runs"]:  # the render and the transition are parts of the step, and both take time
            assert 0 < run["transition_us"] and 0 < run["observe_us"]
            assert run["transition_us"] + run["observe_us"] < run["step_us"]
    one, vec = r["one_env_same_episodes"], r["vector16"]
    assert r["vector16_over_one_env"] == round(one["step_us"] / vec["step_us"], 3)
    bound = one["step_us"] / (vec["step_us"] - vec["transition_us"])
    assert r["vector16_over_one_env_without_transitions"] == round(bound, 3) > r["vector16_over_one_env"]
    assert (DSGWorldEnv._transition, DSGWorldEnv._observe, DSGWorldVectorEnv._observe) == classes
