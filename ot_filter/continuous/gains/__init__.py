"""Gain approximations of the feedback particle filter (the contract is in ``base``)."""

from ot_filter.continuous.gains.base import (
    ConstantGainInfo,
    Gain,
    GainOutput,
    constant_gain,
    function_gain,
    gain_and_correction,
    stratonovich_correction,
)
from ot_filter.continuous.gains.kernel import KernelGainInfo, KernelGainState, kernel_gain
from ot_filter.continuous.gains.learned import LearnedGainInfo, LearnedGainState, learned_gain

__all__ = [
    "ConstantGainInfo",
    "Gain",
    "GainOutput",
    "KernelGainInfo",
    "KernelGainState",
    "LearnedGainInfo",
    "LearnedGainState",
    "constant_gain",
    "function_gain",
    "gain_and_correction",
    "kernel_gain",
    "learned_gain",
    "stratonovich_correction",
]
