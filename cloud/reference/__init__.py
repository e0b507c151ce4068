"""The thesis's own inference methods, kept as references to reproduce and to measure against.

* :mod:`.cross_entropy` — fleet calibration by Cross-Entropy optimisation with injections (§2.4);
* :mod:`.mcmc` — the Bayesian profile and vehicle properties by Metropolis-within-Gibbs (§4.3),
  plus the exact Gaussian posterior of the same model for fixed vehicles, and the bridge's element
  second moments of area with the vehicles' weights (§4.5.4).
* :mod:`.rail_cross_entropy` — a carriage's run properties over a batch of runs by Cross-Entropy
  with restarts (§3.4.1), on the rail calibration's own inverse and mapping.

They are deliberately faithful rather than fast; the production estimators live in ``cloud/road``,
``cloud/bridge`` and ``cloud/rail``. Nothing in the daemons imports this package: what the two share
(the inverse for a population of parameter sets, :func:`population_aps`) lives in ``shared``.
"""

from shared.dynamics.population import population_aps

from cloud.reference.cross_entropy import cross_entropy_fleet, fleet_aps, fleet_objective, objective
from cloud.reference.mcmc import (THESIS_PROPOSAL_SD, BridgeMcmcResult, McmcResult, ProfilePosterior, exact_profile_posterior, forward_channels,
                   mcmc_bridge_elements, mcmc_profile_and_vehicles, response_matrix)

__all__ = [
    "BridgeMcmcResult",
    "mcmc_bridge_elements",
    "McmcResult",
    "ProfilePosterior",
    "THESIS_PROPOSAL_SD",
    "cross_entropy_fleet",
    "exact_profile_posterior",
    "fleet_aps",
    "fleet_objective",
    "forward_channels",
    "mcmc_profile_and_vehicles",
    "objective",
    "population_aps",
    "response_matrix",
]
