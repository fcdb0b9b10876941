"""The chapter's experiments as functions returning numbers and writing figures, callable from
benchmark scripts, the command line and notebooks alike."""

from ot_filter.experiments.static_example import plot_static_example, run_static_example
from ot_filter.experiments.twin_configurations import (
    TWIN_CONFIGURATIONS,
    TWIN_EXPERIMENTS,
    TwinConfiguration,
    TwinExperiment,
    twin_model,
)

__all__ = [
    "TWIN_CONFIGURATIONS",
    "TWIN_EXPERIMENTS",
    "TwinConfiguration",
    "TwinExperiment",
    "plot_static_example",
    "run_static_example",
    "twin_model",
]
