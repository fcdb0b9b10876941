"""Continuous-time filtering: SDE models, the Kalman-Bucy filter and the feedback particle filter.

``SDEModel`` describes dX = a dt + b dB, dY = h dt + sigma dW; ``simulate_sde`` draws a path and
its observation increments on a time grid; ``kalman_bucy`` is exact for the linear model;
``run_fpf`` filters the increments with a ``Gain`` (``constant_gain``, ``kernel_gain``,
``learned_gain``, ``function_gain``); ``discretise`` gives the Euler-Maruyama ``StateSpaceModel``
on which the discrete-time updates (EnKF, SIR, OT) run on the same data
(``run_filter(..., update_first=True)``).
"""

from ot_filter.continuous.fpf import FPFResult, fpf_step, run_fpf
from ot_filter.continuous.gains import (
    ConstantGainInfo,
    Gain,
    GainOutput,
    KernelGainInfo,
    KernelGainState,
    LearnedGainInfo,
    LearnedGainState,
    constant_gain,
    function_gain,
    kernel_gain,
    learned_gain,
)
from ot_filter.continuous.kalman_bucy import KalmanBucyResult, kalman_bucy
from ot_filter.continuous.models import (
    LinearSDEParameters,
    lorenz63_sde,
    ornstein_uhlenbeck,
    squared_observation_sde,
)
from ot_filter.continuous.sde import SDEModel, SDEPath, discretise, sde_dimensions, simulate_sde

__all__ = [
    "ConstantGainInfo",
    "FPFResult",
    "Gain",
    "GainOutput",
    "KalmanBucyResult",
    "KernelGainInfo",
    "KernelGainState",
    "LearnedGainInfo",
    "LearnedGainState",
    "LinearSDEParameters",
    "SDEModel",
    "SDEPath",
    "constant_gain",
    "discretise",
    "fpf_step",
    "function_gain",
    "kalman_bucy",
    "kernel_gain",
    "learned_gain",
    "lorenz63_sde",
    "ornstein_uhlenbeck",
    "run_fpf",
    "sde_dimensions",
    "simulate_sde",
    "squared_observation_sde",
]
