"""Everything that makes a world: synthetic dual-state data, capture loading, training, evaluation."""

import os as _os

import numba as _numba

# Training never forks worker processes: it always uses the OpenMP threading layer (the runtime takes
# numba's own choice and guards forks; see dsg_gym.splat.threads). Must happen before any kernel runs.
if "NUMBA_THREADING_LAYER" not in _os.environ:
    _numba.config.THREADING_LAYER = "omp"

# How torch's and numba's OpenMP pools wait between parallel regions: before either loads OpenMP
from train_world import _openmp

_openmp.configure()
