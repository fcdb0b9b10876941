"""Bayes updates: each a builder returning ``BayesUpdate(init, apply)``."""

from ot_filter.updates.base import (
    BayesUpdate,
    UniformWeightsState,
    active_mask,
    count_active,
    uniform_log_weights,
)
from ot_filter.updates.enkf import EnKFInfo, enkf
from ot_filter.updates.ot import OTInfo, OTState, OTUpdate, ot
from ot_filter.updates.resampling import RESAMPLING_SCHEMES, resample_indices
from ot_filter.updates.sir import SIRInfo, SIRState, sir

__all__ = [
    "BayesUpdate",
    "EnKFInfo",
    "OTInfo",
    "OTState",
    "OTUpdate",
    "RESAMPLING_SCHEMES",
    "SIRInfo",
    "SIRState",
    "UniformWeightsState",
    "active_mask",
    "count_active",
    "enkf",
    "ot",
    "resample_indices",
    "sir",
    "uniform_log_weights",
]
