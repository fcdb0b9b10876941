"""Standardised coordinates and the smoothed prior of the OT update.

The OT update trains and applies its map in standardised coordinates (per coordinate, particles
and simulated observations centred and scaled by their active-particle mean and standard
deviation), so that its defaults do not depend on the problem's scale.

Smoothed bootstrap: the mini-batches are drawn from a kernel-smoothed prior,
``sqrt(1 - h^2) x + h L eps`` with L L^T the particles' correlation matrix (Liu and West's
shrinkage: the mean and covariance are kept) and h = c (4 / (n + 2))^(1/(n+4)) k^(-1/(n+4))
(Silverman's rule times c, k active particles), capped at ``MAX_SMOOTHING_BANDWIDTH``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import masked_mean_and_std

Array = jax.Array

__all__ = [
    "CORRELATION_RIDGE",
    "MAX_SMOOTHING_BANDWIDTH",
    "Standardisation",
    "correlation_cholesky",
    "identity_standardisation",
    "smoothed_draw",
    "smoothing_bandwidth",
    "standardisation",
]

# Cap of the smoothing bandwidth (standardised units): the particles then keep 19% of the
# variance (sqrt(1 - 0.81)^2) and the jitter supplies the rest.
MAX_SMOOTHING_BANDWIDTH = 0.9
# Ridge on the particles' correlation matrix before its Cholesky factor (degenerate ensembles).
CORRELATION_RIDGE = 1e-6


class Standardisation(NamedTuple):
    x_mean: Array  # [n]
    x_scale: Array  # [n]
    y_mean: Array  # [m]
    y_scale: Array  # [m]

    def standardise_x(self, x: Array) -> Array:
        return (x - self.x_mean) / self.x_scale

    def standardise_y(self, y: Array) -> Array:
        return (y - self.y_mean) / self.y_scale

    def restore_x(self, x_standard: Array) -> Array:
        return x_standard * self.x_scale + self.x_mean

    def restore_y(self, y_standard: Array) -> Array:
        return y_standard * self.y_scale + self.y_mean


def identity_standardisation(n: int, m: int, dtype) -> Standardisation:
    return Standardisation(jnp.zeros(n, dtype), jnp.ones(n, dtype), jnp.zeros(m, dtype), jnp.ones(m, dtype))


def standardisation(particles: Array, simulated: Array, active: Array) -> Standardisation:
    """Active-particle means and standard deviations of ``particles[N, n]`` and
    ``simulated[N, m]``; a constant coordinate gets scale 1 (any positive scale will do)."""

    def mean_and_scale(values):
        mean, std = masked_mean_and_std(values, active)
        return mean, jnp.where(std > 0, std, jnp.ones_like(std))

    return Standardisation(*mean_and_scale(particles), *mean_and_scale(simulated))


def smoothing_bandwidth(smoothing, num_active: Array, n: int, dtype) -> Array:
    """h = min(c (4 / (n + 2))^(1/(n+4)) k^(-1/(n+4)), ``MAX_SMOOTHING_BANDWIDTH``)."""
    silverman = (4.0 / (n + 2)) ** (1.0 / (n + 4)) * jnp.asarray(num_active, dtype) ** (-1.0 / (n + 4))
    return jnp.minimum(smoothing * silverman, MAX_SMOOTHING_BANDWIDTH)


def correlation_cholesky(standardised: Array, active: Array | None = None) -> Array:
    """Cholesky factor ``[n, n]`` of the correlation matrix of standardised particles ``[N, n]``
    (the rows where ``active`` is True, if given)."""
    num, n = standardised.shape
    if active is not None:
        num = jnp.sum(active).astype(standardised.dtype)
        standardised = jnp.where(active[:, None], standardised, 0.0)
    correlation = standardised.T @ standardised / num
    ridge = CORRELATION_RIDGE * jnp.eye(n, dtype=standardised.dtype)
    return jnp.linalg.cholesky(0.5 * (correlation + correlation.T) + ridge)


def smoothed_draw(key: Array, x: Array, bandwidth, correlation_factor: Array) -> Array:
    """A draw from the shrunk Gaussian kernel density estimate around standardised ``x[B, n]``:
    sqrt(1 - h^2) x + h L eps with L L^T the particles' correlation matrix, so that the smoothed
    prior keeps the particles' mean (0) and covariance (Liu and West's shrinkage)."""
    noise = jax.random.normal(key, x.shape, x.dtype) @ correlation_factor.T
    return (1.0 - bandwidth**2) ** 0.5 * x + bandwidth * noise
