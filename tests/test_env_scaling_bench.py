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


def test_breakdown_on_given_steppers_leaves_them_open_and_unwrapped():
    from benchmarks.env_scaling import Stepper, breakdown_section

    one, vec = Stepper(1, 64, episodes=16), Stepper(16, 64)
    r = breakdown_section(32, 1, one, vec)
    assert r["vector16"]["transition_us"] > 0 and r["one_env_same_episodes"]["observe_us"] > 0
    for s in (one, vec):  # the timing wrappers are gone and the env still steps
        assert not {"_observe", "_transition"} & set(vars(s.env.unwrapped))
        assert not any("_transition" in vars(m) for m in s.members)
        assert "reset" not in vars(s.env)
        assert s.run(4, keep=False) > 0
        s.env.close()
