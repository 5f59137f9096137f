r"""Neural Modes (Wang et al. 2024): linear modes, the nonlinear modal map, its training, its ground truth.

The method in one line per module:

- :mod:`~latentsim.neural_modes.linear`: linear modes K e = omega^2 M e (Sec. 3.2), with the rigid
  modes of a free-floating object removed, or the Dirichlet DoFs fixed;
- :mod:`~latentsim.neural_modes.network`: the map n(z) = X + l(z) + y(z) (Eq. 10-11), y a GELU MLP;
- :mod:`~latentsim.neural_modes.training`: the self-supervised loss (Eq. 12-13), modal samples,
  the optimiser and the training loop;
- :mod:`~latentsim.neural_modes.compliant_modes`: the ground truth of Eq. 9, the nonlinear compliant
  modes, solved per sample by ``latentsim.solve.constrained``;
- :mod:`~latentsim.neural_modes.directions`: the latent directions at the origin and their
  correlation (mode collapse, Fig. 4);
- the evaluation studies of Sec. 4: :mod:`~latentsim.neural_modes.sheet` (Sec. 4.1-4.4, the square
  sheet), :mod:`~latentsim.neural_modes.energy_study` (Table 5), :mod:`~latentsim.neural_modes.dynamics`
  (subspace dynamics, Eq. 15), :mod:`~latentsim.neural_modes.aspect` (Sec. 4.3, aspect ratio).

Settings are the config schema's ``neural_modes`` definition (``workflow/schemas/config.schema.yaml``);
functions given a partial settings dict fill it from the schema's defaults
(``latentsim.config.with_defaults``).
"""

from latentsim.neural_modes.compliant_modes import ground_truth
from latentsim.neural_modes.directions import direction_correlation, latent_directions
from latentsim.neural_modes.linear import LinearModes, fixed_dofs, linear_modes, rigid_modes
from latentsim.neural_modes.network import NeuralModes, from_config, load_neural_modes, neural_modes_from_state
from latentsim.neural_modes.training import make_optimizer, modal_samples, neural_modes_loss, train_neural_modes

__all__ = [
    "LinearModes",
    "NeuralModes",
    "direction_correlation",
    "fixed_dofs",
    "from_config",
    "ground_truth",
    "latent_directions",
    "linear_modes",
    "load_neural_modes",
    "make_optimizer",
    "modal_samples",
    "neural_modes_from_state",
    "neural_modes_loss",
    "rigid_modes",
    "train_neural_modes",
]
