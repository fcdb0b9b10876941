"""Exact reference posteriors on a 1-D grid.

For models whose posterior factorises over coordinates (the chapter's squared-observation
examples) each coordinate's posterior is a 1-D density known up to a constant,
p(x | y) ∝ p(x) l(y | x). On a fine uniform grid it is normalised by the trapezoid rule and its
CDF accumulated; the error is the quadrature error (O(dx^2) for smooth densities) plus the mass
outside the grid, which ``grid_posterior`` reports so that a too-narrow grid is visible.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = ["GridDensity", "grid_posterior", "squared_observation_posterior"]


class GridDensity(NamedTuple):
    grid: Array  # [G] uniform grid
    density: Array  # [G] normalised density on the grid
    cdf: Array  # [G] cumulative distribution (trapezoid), cdf[-1] = 1
    edge_mass: Array  # density at the two ends times the grid span: should be ~0


def grid_posterior(log_density: Callable[[Array], Array], lower: float, upper: float,
                   num_points: int = 20_001) -> GridDensity:
    """Normalises ``exp(log_density(grid))`` on a uniform grid of ``num_points`` in [lower, upper]."""
    if not upper > lower:
        raise ValueError(f"upper must be > lower, got [{lower}, {upper}]")
    if num_points < 3:
        raise ValueError(f"num_points must be >= 3, got {num_points}")
    grid = jnp.linspace(lower, upper, num_points)
    log_values = log_density(grid)
    values = jnp.exp(log_values - jnp.max(log_values))
    spacing = grid[1] - grid[0]
    cumulative = jnp.concatenate([jnp.zeros(1), jnp.cumsum(0.5 * (values[1:] + values[:-1]) * spacing)])
    total = cumulative[-1]
    density = values / total
    edge_mass = (density[0] + density[-1]) * (upper - lower)
    return GridDensity(grid, density, cumulative / total, edge_mass)


def squared_observation_posterior(observation: float, noise: float, scale: float = 0.5,
                                  prior_mean: float = 0.0, prior_std: float = 1.0,
                                  width: float = 8.0, num_points: int = 20_001) -> GridDensity:
    """Posterior of X ~ N(prior_mean, prior_std^2) given y = scale X^2 + noise W, on a grid of
    ``prior_mean +- width * prior_std`` (the static example: scale 0.5, N(0, 1))."""
    if not (noise > 0 and prior_std > 0):
        raise ValueError(f"noise and prior_std must be > 0, got {noise}, {prior_std}")

    def log_density(x):
        return -0.5 * ((x - prior_mean) / prior_std) ** 2 - 0.5 * ((observation - scale * x * x) / noise) ** 2

    return grid_posterior(log_density, prior_mean - width * prior_std, prior_mean + width * prior_std,
                          num_points)
