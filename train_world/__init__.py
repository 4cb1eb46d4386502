"""Everything that makes a world: synthetic dual-state data, capture loading, training, evaluation."""

import os as _os

import numba as _numba

# Training never forks worker processes, so it can use the faster OpenMP threading layer (the runtime
# defaults to the fork-safe workqueue layer; see dsg_gym.splat). Must happen before any kernel runs.
if "NUMBA_THREADING_LAYER" not in _os.environ:
    _numba.config.THREADING_LAYER = "omp"
