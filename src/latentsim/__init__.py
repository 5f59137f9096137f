"""latentsim: full-space simulation, latent-space dynamics and Neural Modes in one pipeline."""

__version__ = "0.1.0"
