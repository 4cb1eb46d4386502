"""dsg-gym: dual-state Gaussian world models as Gymnasium environments."""

__version__ = "0.3.0"

from . import envs as _envs  # noqa: E402,F401  registers DSGWorld-v0 (light: no MuJoCo/numba at import)
