"""latentsim: full-space simulation, latent-space dynamics and Neural Modes in one pipeline."""

import os as _os

# MKL (PARDISO), OpenMP and torch threads fight over few cores when idle threads spin; this must be
# set before numpy/torch start their thread pools, so it lives here, before any submodule imports them.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
_os.environ.setdefault("KMP_BLOCKTIME", "0")

__version__ = "0.1.0"
