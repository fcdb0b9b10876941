"""Built-in state-space models."""

from ot_filter.models.linear_gaussian import LinearGaussianParameters, linear_gaussian
from ot_filter.models.lorenz import (
    lorenz63,
    lorenz63_vector_field,
    lorenz96,
    lorenz96_vector_field,
)
from ot_filter.models.squared_observation import squared_observation

__all__ = [
    "LinearGaussianParameters",
    "linear_gaussian",
    "lorenz63",
    "lorenz63_vector_field",
    "lorenz96",
    "lorenz96_vector_field",
    "squared_observation",
]
