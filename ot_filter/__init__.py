"""ot_filter: nonlinear filtering and Bayesian posterior sampling in JAX.

Models are pytrees of per-particle functions (``StateSpaceModel``); Bayes updates are builders
returning ``BayesUpdate(init, apply)`` (``sir``, ``enkf``, ``ot``); ``run_filter`` composes them into a
whole-trajectory filter in one ``lax.scan``; ``kalman_filter`` is the exact reference. ``continuous`` holds the continuous-time part
(``SDEModel``, Kalman-Bucy, the feedback particle filter and its gains).
"""

from ot_filter import continuous, metrics, models, reference
from ot_filter.continuous import SDEModel
from ot_filter.filtering import FilterResult, run_filter
from ot_filter.kalman import KalmanResult, kalman_filter
from ot_filter.model import StateSpaceModel, simulate
from ot_filter.sharding import particle_sharding
from ot_filter.updates import (
    BayesUpdate,
    EnKFInfo,
    OTInfo,
    OTState,
    OTUpdate,
    SIRInfo,
    SIRState,
    enkf,
    ot,
    resample_indices,
    sir,
)

__version__ = "0.1.0"

__all__ = [
    "BayesUpdate",
    "EnKFInfo",
    "FilterResult",
    "KalmanResult",
    "OTInfo",
    "OTState",
    "OTUpdate",
    "SIRInfo",
    "SIRState",
    "SDEModel",
    "StateSpaceModel",
    "continuous",
    "enkf",
    "kalman_filter",
    "metrics",
    "models",
    "ot",
    "particle_sharding",
    "reference",
    "resample_indices",
    "run_filter",
    "simulate",
    "sir",
]
