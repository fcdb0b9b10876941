"""Exact reference posteriors on a 1-D grid.

For models whose posterior factorises over coordinates (the chapter's squared-observation
examples) each coordinate's posterior is a 1-D density known up to a constant,
p(x | y) ∝ p(x) l(y | x). On a fine uniform grid it is normalised by the trapezoid rule and its
CDF accumulated; the error is the quadrature error (O(dx^2) for smooth densities) plus the mass
outside the grid, which ``grid_posterior`` reports so that a too-narrow grid is visible.

Filtering (``grid_filter``): for a 1-D state with a Gaussian transition x' ~ N(m(x), s^2) the
filtering distribution is propagated on the grid by the transition matrix
K[i, j] = N(g_i; m(g_j), s^2) dx and multiplied by the likelihood at every observation: exact up
to the O(dx^2) quadrature error and the mass that leaves the grid (reported). The chapter's
dynamic example is separable, so its exact posterior is the product over coordinates of such 1-D
filters (``squared_observation_filter``). Unlike a large SIR reference, this has no Monte-Carlo
drift between the two mirror-image modes: each coordinate keeps mass exactly 1/2 on each side.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = [
    "GridDensity",
    "GridFilter",
    "grid_filter",
    "grid_posterior",
    "poisson_gain_1d",
    "squared_observation_filter",
    "squared_observation_posterior",
]


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


class GridFilter(NamedTuple):
    grid: Array  # [G] uniform grid
    masses: Array  # [..., T, G] posterior probability of each grid node after each observation
    lost_mass: Array  # [..., T] prior mass the transition moved off the grid (should be ~0)


def grid_filter(
    log_likelihood: Callable[[Array, Array], Array],
    observations: Array,
    grid: Array,
    initial_log_density: Callable[[Array], Array],
    transition_mean: Callable[[Array], Array],
    transition_std: float,
) -> GridFilter:
    """Exact (to grid error) 1-D filter: X_0 ~ pi_0, X_t ~ N(m(X_{t-1}), s^2), y_t ~ l(. | X_t).

    Args:
      log_likelihood: ``(y, x[G]) -> [G]`` log l(y | x) at the grid nodes (up to a constant).
      observations: ``[T]`` or ``[T, k]`` observations y_1..y_T of this coordinate.
      grid: ``[G]`` uniform grid wide enough to hold the filtering distributions.
      initial_log_density: ``x[G] -> [G]`` log pi_0 up to a constant.
      transition_mean: ``x[G] -> [G]`` the mean m(x) of the Gaussian transition.
      transition_std: s > 0.

    Returns:
      ``GridFilter`` with the posterior masses ``[T, G]`` after each of the T observations.
    """
    grid = jnp.asarray(grid)
    if grid.ndim != 1 or grid.shape[0] < 3:
        raise ValueError(f"grid must have shape [G >= 3], got {grid.shape}")
    if not transition_std > 0:
        raise ValueError(f"transition_std must be > 0, got {transition_std}")
    spacing = grid[1] - grid[0]
    # K[i, j] = N(g_i; m(g_j), s^2) dx: column j spreads node j's mass over the grid.
    standardised = (grid[:, None] - transition_mean(grid)[None, :]) / transition_std
    kernel = jnp.exp(-0.5 * standardised**2) * spacing / (jnp.sqrt(2 * jnp.pi) * transition_std)
    log_prior = initial_log_density(grid)
    masses = jnp.exp(log_prior - jnp.max(log_prior))
    masses = masses / jnp.sum(masses)

    def step(masses, observation):
        predicted = kernel @ masses
        lost = 1.0 - jnp.sum(predicted)
        log_posterior = jnp.log(predicted) + log_likelihood(observation, grid)
        posterior = jnp.exp(log_posterior - jnp.max(log_posterior))
        posterior = posterior / jnp.sum(posterior)
        return posterior, (posterior, lost)

    _, (masses, lost) = jax.lax.scan(step, masses, jnp.asarray(observations, grid.dtype))
    return GridFilter(grid, masses, lost)


def squared_observation_filter(
    observations: Array,
    noise: float = 0.1**0.5,
    alpha: float = 0.1,
    process_noise_std: float | None = None,
    scale: float = 1.0,
    width: float = 9.0,
    num_points: int = 901,
) -> GridFilter:
    """Exact posterior of the chapter's dynamic example (``models.squared_observation``):
    X_0 ~ N(0, I), X_t = (1 - alpha) X_{t-1} + s V_t, y_t = scale X_t (.) X_t + noise W_t.

    Args:
      observations: ``[T, n]`` (one column per coordinate; each is filtered separately).
      process_noise_std: s (default ``2 * noise``, as the model).
      width, num_points: the grid ``[-width, width]`` with ``num_points`` nodes (the default
        spacing 0.02 resolves the likelihood's narrowest mode, about noise / (2 sqrt(y)) wide).

    Returns:
      ``GridFilter`` with masses ``[n, T, G]``: coordinate d's posterior after each observation;
      the joint posterior is their product.
    """
    observations = jnp.asarray(observations)
    if observations.ndim != 2:
        raise ValueError(f"observations must have shape [T, n], got {observations.shape}")
    if not noise > 0:
        raise ValueError(f"noise must be > 0, got {noise}")
    if process_noise_std is None:
        process_noise_std = 2.0 * noise
    grid = jnp.linspace(-width, width, num_points, dtype=observations.dtype)

    def filter_coordinate(column):
        return grid_filter(
            lambda y, x: -0.5 * ((y - scale * x * x) / noise) ** 2,
            column,
            grid,
            lambda x: -0.5 * x * x,
            lambda x: (1.0 - alpha) * x,
            process_noise_std,
        )

    result = jax.vmap(filter_coordinate)(observations.T)
    return GridFilter(grid, result.masses, result.lost_mass)


def poisson_gain_1d(density: GridDensity, h_values: Array) -> Array:
    """The exact FPF gain K = phi' of a 1-D density on its grid, by quadrature.

    The Poisson equation -(p phi')' = p (h - h_hat) integrates once to
    K(x) = -(1 / p(x)) int_{-inf}^x (h(s) - h_hat) p(s) ds = (1 / p(x)) int_x^inf (...) ds
    (trapezoid rule on the grid, h_hat = int h p / int p). Each node uses the integral over the
    nearer tail (less than half the mass): dividing a difference of two O(1) integrals by the tiny
    p of the far tail would magnify their rounding. ``h_values``: h at the grid nodes ``[G]``.
    Returns K at the nodes ``[G]``; where p is below 1e-300 (float64; 1e-30 in float32) relative
    to its peak (far tails) K is set to 0.
    """
    grid, p = density.grid, density.density
    spacing = grid[1] - grid[0]

    def cumulative(values):  # int_{grid[0]}^{grid[i]}
        pieces = 0.5 * (values[1:] + values[:-1]) * spacing
        return jnp.concatenate([jnp.zeros(1, values.dtype), jnp.cumsum(pieces)])

    def cumulative_from_right(values):  # int_{grid[i]}^{grid[-1]}
        return cumulative(values[::-1])[::-1]

    mass = cumulative(p)
    h_hat = cumulative(h_values * p)[-1] / mass[-1]
    forcing = (h_values - h_hat) * p
    flux = jnp.where(
        mass <= 0.5 * mass[-1], -cumulative(forcing), cumulative_from_right(forcing)
    )
    tiny = jnp.max(p) * 1e-300 if p.dtype == jnp.float64 else jnp.max(p) * 1e-30
    return jnp.where(p > tiny, flux / jnp.maximum(p, tiny), 0.0)
