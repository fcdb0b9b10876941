"""The optimal-transport Bayes update's building blocks: networks, saddle-point training,
diagnostics. ``ot_filter.ot`` (in ``updates/ot.py``) assembles them into a ``BayesUpdate``."""

from ot_filter.transport.diagnostics import c_concavity_min_eigenvalue
from ot_filter.transport.networks import ACTIVATIONS, PotentialNetwork, TransportNetwork
from ot_filter.transport.saddle import (
    SaddleParams,
    TrainingState,
    TrainingTrace,
    enkf_gain,
    saddle_objective,
    train_saddle,
)

__all__ = [
    "ACTIVATIONS",
    "PotentialNetwork",
    "SaddleParams",
    "TrainingState",
    "TrainingTrace",
    "TransportNetwork",
    "c_concavity_min_eigenvalue",
    "enkf_gain",
    "saddle_objective",
    "train_saddle",
]
