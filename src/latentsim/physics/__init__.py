"""Energies, written once: every solver, loss and metric calls these."""
