"""Reporting: what the evaluation measures, tabulates and draws.

- :mod:`latentsim.report.metrics`: errors, kinetic energy, Pareto front (NumPy only);
- :mod:`latentsim.report.tables`: Li et al. Tables 1-2, stability, sizes, glance tables (pandas);
- :mod:`latentsim.report.plots`: charts (matplotlib); the Neural Modes studies' own figures are
  :mod:`latentsim.neural_modes.figures`;
- :mod:`latentsim.report.motion`: a sequence of a trajectory file; :mod:`latentsim.report.render`:
  frames and clips of it; :mod:`latentsim.report.paraview`: its ParaView series;
- :mod:`latentsim.report.paper`: the papers' printed numbers.

Import the submodules themselves: this package imports none of them, so reading the metrics or
tables never loads matplotlib.  The evaluation stages that call them are :mod:`latentsim.stages.evaluate`.
"""
