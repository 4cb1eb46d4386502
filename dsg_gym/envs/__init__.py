"""Gymnasium environments. ``DSGWorld-v0`` (:class:`~dsg_gym.envs.dsg_world.DSGWorldEnv`, with its own vector
env :class:`~dsg_gym.envs.dsg_world_vector.DSGWorldVectorEnv` for ``gymnasium.make_vec(...,
vectorization_mode="vector_entry_point")``) and ``DSGWorldGoal-v0`` (:class:`~dsg_gym.envs.goal_env.DSGWorldGoalEnv`,
its goal-conditioned observation for hindsight relabelling) are registered when ``dsg_gym`` is imported;
importing this package is light (MuJoCo and the renderer load with the env)."""

import gymnasium

__all__ = ["register_envs", "ENV_ID", "GOAL_ENV_ID", "MAX_EPISODE_STEPS"]

ENV_ID = "DSGWorld-v0"
GOAL_ENV_ID = "DSGWorldGoal-v0"
MAX_EPISODE_STEPS = 200


def register_envs() -> None:
    """Register ``DSGWorld-v0`` and ``DSGWorldGoal-v0`` (idempotent)."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(
            id=ENV_ID,
            entry_point="dsg_gym.envs.dsg_world:DSGWorldEnv",
            vector_entry_point="dsg_gym.envs.dsg_world_vector:DSGWorldVectorEnv",
            max_episode_steps=MAX_EPISODE_STEPS,
        )
    if GOAL_ENV_ID not in gymnasium.registry:
        gymnasium.register(
            id=GOAL_ENV_ID,
            entry_point="dsg_gym.envs.goal_env:DSGWorldGoalEnv",
            max_episode_steps=MAX_EPISODE_STEPS,
        )


register_envs()
