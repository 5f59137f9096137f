"""latentsim: full-space simulation, latent-space dynamics and Neural Modes in one pipeline."""

import os as _os

# MKL (PARDISO), OpenMP and torch threads fight over few cores when idle threads spin; this must be
# set before numpy/torch start their thread pools, so it lives here, before any submodule imports them.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
_os.environ.setdefault("KMP_BLOCKTIME", "0")
# OpenBLAS threads only slow down the many small dense products (reduced solvers, r x r systems):
# measured ~10x on the cloth's Fulton-style reduced step with two busy cores.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
