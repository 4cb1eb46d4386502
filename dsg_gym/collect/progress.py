"""The progress bar of a collection run and its two rates, each named for what it measures:

- **rollout** ``env steps/s``: transitions per second of rollout time (resets, policy and env steps), shard
  writes excluded; the speed of policy and env alone;
- **overall** ``episodes/s``: episodes finished per second since the run started, env start-up and dataset
  writes included; the speed at which a dataset grows.

The rollout rate divided by the episode length bounds the overall rate from above; the gap is start-up and
writing.
"""

from __future__ import annotations

import time

from .rollout import EpisodeRecord

__all__ = ["Progress"]

_BAR = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} episodes [{elapsed}<{remaining}{postfix}]"


class Progress:
    """A tqdm bar over the run's episodes (none when ``enabled`` is false) showing both rates and the success
    rate. ``t_start``: when the run started (``time.monotonic()``), for the overall rate."""

    def __init__(self, enabled: bool, total: int, done: int, successes: int, t_start: float):
        self.bar = None
        self.done0, self.total_done, self.succ = done, done, successes
        self.t_start, self.shown = t_start, 0.0
        self.t_rollout: float | None = None  # when the rollout started (its first ``steps`` call)
        self.rollout_steps, self.write_s = 0, 0.0
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=done, desc="collect", bar_format=_BAR, dynamic_ncols=True)

    def episode(self, rec: EpisodeRecord) -> None:
        self.set_done(self.total_done + 1, self.succ + int(rec.success))

    def set_done(self, done: int, successes: int) -> None:
        """``done`` of the run's episodes are finished, ``successes`` of them successful."""
        if self.bar is not None and done > self.total_done:
            self.bar.update(done - self.total_done)
        self.total_done, self.succ = done, successes
        self._postfix(force=True)

    def steps(self, n: int) -> None:
        """``n`` env steps (transitions) were taken; ``steps(0)`` marks the start of the rollout."""
        if self.t_rollout is None:
            self.t_rollout = time.monotonic()
        self.rollout_steps += n
        self._postfix()

    def wrote(self, seconds: float) -> None:
        """A shard write took ``seconds`` (not rollout time)."""
        self.write_s += seconds

    def rates(self) -> str:
        now = time.monotonic()
        parts = []
        if self.t_rollout is not None and self.rollout_steps:
            rollout_s = max(now - self.t_rollout - self.write_s, 1e-9)
            parts.append(f"rollout {self.rollout_steps / rollout_s:.0f} env steps/s")
        parts.append(
            f"overall {(self.total_done - self.done0) / max(now - self.t_start, 1e-9):.2f} episodes/s"
        )
        if self.total_done:
            parts.append(f"success {self.succ / self.total_done:.0%}")
        return ", ".join(parts)

    def _postfix(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.bar is None or (not force and now - self.shown < 0.5):
            return
        self.shown = now
        self.bar.set_postfix_str(self.rates(), refresh=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
