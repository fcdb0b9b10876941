"""Bayes updates: each a builder returning ``BayesUpdate(init, apply)``."""

from ot_filter.updates.averaged_maps import AveragedMapsInfo, AveragedMapsState, AveragedMapsUpdate, averaged_maps
from ot_filter.updates.base import (
    BayesUpdate,
    UniformWeightsState,
    active_mask,
    count_active,
    uniform_log_weights,
)
from ot_filter.updates.enkf import EnKFInfo, EnKFSettings, enkf
from ot_filter.updates.flow_matching import FlowInfo, FlowSettings, FlowState, FlowStructure, FlowUpdate, flow_matching
from ot_filter.updates.letkf import LETKFInfo, LETKFSettings, letkf
from ot_filter.updates.local_etpf import LocalETPFInfo, LocalETPFSettings, local_etpf
from ot_filter.updates.local_flow import LocalFlowSettings, LocalFlowState, LocalFlowUpdate, local_flow
from ot_filter.updates.local_ot import LocalOTSettings, LocalOTState, LocalOTUpdate, local_ot
from ot_filter.updates.ot import OTInfo, OTSettings, OTState, OTStructure, OTUpdate, ot
from ot_filter.updates.resampling import RESAMPLING_SCHEMES, resample_indices
from ot_filter.updates.sir import SIRInfo, SIRSettings, SIRState, sir
from ot_filter.updates.tempering import SplitLikelihoodInfo, SplitLikelihoodState, split_likelihood, tempered_model

__all__ = [
    "AveragedMapsInfo",
    "AveragedMapsState",
    "AveragedMapsUpdate",
    "BayesUpdate",
    "EnKFInfo",
    "EnKFSettings",
    "FlowInfo",
    "FlowSettings",
    "FlowState",
    "FlowStructure",
    "FlowUpdate",
    "LETKFInfo",
    "LETKFSettings",
    "LocalETPFInfo",
    "LocalETPFSettings",
    "LocalFlowSettings",
    "LocalFlowState",
    "LocalFlowUpdate",
    "LocalOTSettings",
    "LocalOTState",
    "LocalOTUpdate",
    "OTInfo",
    "OTSettings",
    "OTState",
    "OTStructure",
    "OTUpdate",
    "RESAMPLING_SCHEMES",
    "SIRInfo",
    "SIRSettings",
    "SIRState",
    "SplitLikelihoodInfo",
    "SplitLikelihoodState",
    "UniformWeightsState",
    "active_mask",
    "averaged_maps",
    "count_active",
    "enkf",
    "flow_matching",
    "letkf",
    "local_etpf",
    "local_flow",
    "local_ot",
    "ot",
    "resample_indices",
    "sir",
    "split_likelihood",
    "tempered_model",
    "uniform_log_weights",
]
