"""Solvers: energy minimisation on the scenes' potentials.

- :mod:`~latentsim.solve.newton`: the one Newton minimiser and Armijo line search every solver runs;
- :mod:`~latentsim.solve.implicit_euler`: full-space implicit Euler (Li et al. 2025, Eq. 1);
- :mod:`~latentsim.solve.reduced`: implicit Euler over any subspace map x = phi(q, x*_D) (Fulton
  et al. 2019), Newton or L-BFGS (the subspaces themselves: :mod:`latentsim.latent.subspaces`,
  :mod:`latentsim.neural_modes.dynamics`);
- :mod:`~latentsim.solve.constrained`: the Neural Modes ground truth under linear constraints
  (Wang et al. 2024, Eq. 9);
- :mod:`~latentsim.solve.modes`: stiffness matrix and linear vibration modes;
- :mod:`~latentsim.solve.assembly`, :mod:`~latentsim.solve.sparse`: the compiled gradient and
  sparse Hessian assembly, the sparse linear solvers;
- :mod:`~latentsim.solve.cubature`: optimised cubature of reduced elastic forces (An et al. 2008).
"""
