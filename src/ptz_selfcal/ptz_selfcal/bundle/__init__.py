"""Bundle adjustment over keyframes (section 5): observations, residuals, Schur solve, covariance.

The public API: the observations (BundleObservations, pair_observations) and the adjuster
(bundle_adjust, default_pp_prior). problem and schur are the adjuster's parts.
"""

from ptz_selfcal.bundle.adjust import bundle_adjust, default_pp_prior
from ptz_selfcal.bundle.observations import BundleObservations, ObservationsLike, pair_observations

__all__ = ["BundleObservations", "ObservationsLike", "bundle_adjust", "default_pp_prior", "pair_observations"]
