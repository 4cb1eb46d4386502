"""Policy data collection: vectorised rollouts of ``DSGWorld-v0`` (or any Box-action Gymnasium env) written as
Minari datasets, resumable, optionally spread over Ray workers. CLI: ``dsg-collect`` (:mod:`dsg_gym.cli.collect`).

```python
from dsg_gym.collect import collect
res = collect("datasets", policy="expert", episodes=100, num_envs=2, seed=0, env_kwargs={"width": 64, "height": 64})
# MINARI_DATASETS_PATH=datasets  ->  minari.load_dataset(res.dataset_id)   (or load(res.path))
```
"""

from .policies import BUILTIN_POLICIES, ExpertPolicy, PolicyError, RandomPolicy, policy_factory
from .rollout import DEFAULT_INFO_KEYS, CollectError, EpisodeRecord, episode_seed, make_vector_env, rollout
from .run import CollectResult, CollectSettingsError, collect, default_dataset_id

__all__ = [
    "BUILTIN_POLICIES",
    "DEFAULT_INFO_KEYS",
    "CollectError",
    "CollectResult",
    "CollectSettingsError",
    "EpisodeRecord",
    "ExpertPolicy",
    "PolicyError",
    "RandomPolicy",
    "collect",
    "default_dataset_id",
    "episode_seed",
    "load",
    "make_vector_env",
    "policy_factory",
    "rollout",
]


def load(path):
    """The :class:`minari.MinariDataset` in a dataset folder written by :func:`collect` (``path`` or
    ``path/data``), without ``MINARI_DATASETS_PATH``."""
    from pathlib import Path

    import minari

    p = Path(path)
    return minari.MinariDataset(p / "data" if (p / "data" / "metadata.json").exists() else p)
