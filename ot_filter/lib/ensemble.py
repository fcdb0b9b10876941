"""Ensemble statistics: means, anomalies, standard deviations and covariances of particles,
equally weighted, masked (only the active rows of a padded particle axis) or weighted.

Masked statistics never let a padding row in (``where``, not a product with 0, so that even inf
or NaN there cannot leak) and divide by the number k of active rows; with every row active their
values are those of the unmasked formulas.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = [
    "masked_mean_and_anomalies",
    "masked_mean_and_std",
    "mean_and_anomalies",
    "weighted_covariance",
    "weighted_variance",
]


def mean_and_anomalies(particles: Array):
    """Mean ``[n]`` and centred anomalies ``[N, n]`` of equally weighted particles."""
    mean = jnp.mean(particles, axis=-2, keepdims=True)
    return mean[..., 0, :], particles - mean


def masked_mean_and_anomalies(particles: Array, active: Array, num_active: Array | None = None):
    """Mean ``[n]`` of the active rows of ``particles[N, n]`` (``active[N]`` bool, ``num_active``
    of them; counted here if not given) and their anomalies ``[N, n]``, with exact zero rows for
    the inactive (padding) ones."""
    if num_active is None:
        num_active = jnp.sum(active, dtype=jnp.int32)
    rows = active[:, None]
    total = jnp.sum(jnp.where(rows, particles, 0.0), axis=0)
    num = particles.shape[0]
    # Nothing padded: total / num on the static num, jnp.mean's own expression (see
    # lib.weights.count_dependent).
    mean = jnp.where(num_active == num, total / num, total / jnp.asarray(num_active, particles.dtype))
    return mean, jnp.where(rows, particles - mean, 0.0)


def masked_mean_and_std(values: Array, active: Array, num_active: Array | None = None):
    """Mean ``[d]`` and (population, divisor k) standard deviation ``[d]`` over the active rows of
    ``values[N, d]``."""
    if num_active is None:
        num_active = jnp.sum(active, dtype=jnp.int32)
    mean, anomalies = masked_mean_and_anomalies(values, active, num_active)
    variance = jnp.sum(anomalies**2, axis=0) / jnp.asarray(num_active, values.dtype)
    return mean, jnp.sqrt(variance)


def weighted_covariance(particles: Array, log_weights: Array) -> Array:
    """Unbiased weighted covariance ``[..., n, n]`` of ``particles[..., N, n]``.

    C = sum_i w_i (x_i - mean)(x_i - mean)^T / (1 - sum_i w_i^2). When (nearly) all the mass sits
    on one particle the factor is 0 / 0; the equally weighted covariance is used instead (as
    DAPPER does), so that a collapsed ensemble still gets a usable spread estimate. Particles of
    log-weight -inf (padding, ``updates.base``) get weight 0, also in that fallback, unless
    fewer than two particles are left (then all count, to stay finite).
    """
    weights, anomalies, denominator = _weighted_anomalies(particles, log_weights)
    covariance = jnp.einsum("...i,...ij,...ik->...jk", weights, anomalies, anomalies)
    return covariance / denominator


def weighted_variance(particles: Array, log_weights: Array) -> Array:
    """The diagonal ``[..., n]`` of ``weighted_covariance``, in O(N n) (no n x n matrix)."""
    weights, anomalies, denominator = _weighted_anomalies(particles, log_weights)
    return jnp.einsum("...i,...ij->...j", weights, anomalies**2) / denominator[..., 0]


def _weighted_anomalies(particles: Array, log_weights: Array):
    """``(weights [..., N], anomalies [..., N, n], 1 - sum w^2 [..., 1, 1])`` of the
    unbiased weighted second moments (``weighted_covariance``'s rules for collapse and padding)."""
    weights = jnp.exp(log_weights - jax.nn.logsumexp(log_weights, axis=-1, keepdims=True))
    eps = jnp.finfo(particles.dtype).eps
    collapsed = 1.0 - jnp.max(weights, axis=-1, keepdims=True) < 100 * eps
    num = particles.shape[-2]
    counted = log_weights > -jnp.inf
    num_counted = jnp.sum(counted, axis=-1, keepdims=True)
    counted = counted | (num_counted < 2)
    num_counted = jnp.sum(counted, axis=-1, keepdims=True)
    # 1.0 / num as a Python constant when nothing is padded: bit for bit the unpadded fallback.
    equal = jnp.where(
        num_counted == num, 1.0 / num, counted / num_counted.astype(weights.dtype)
    ).astype(weights.dtype)
    weights = jnp.where(collapsed, equal, weights)
    mean = jnp.einsum("...i,...ij->...j", weights, particles)
    anomalies = particles - mean[..., None, :]
    sum_squared = jnp.sum(weights**2, axis=-1)[..., None, None]
    return weights, anomalies, 1.0 - sum_squared


def inflate(particles: Array, active: Array, inflation, mean_and_anomalies=None) -> Array:
    """Multiplicative inflation of the anomalies about the active rows' mean: mean + inflation
    (x - mean); inflation 1 leaves the particles exactly as they are (no ulp change).
    ``mean_and_anomalies``: ``masked_mean_and_anomalies`` of the particles, where the caller has
    them (the EnKF's hot path: not computed twice)."""
    if mean_and_anomalies is None:
        mean_and_anomalies = masked_mean_and_anomalies(particles, active, jnp.sum(active, dtype=jnp.int32))
    mean, anomalies = mean_and_anomalies
    return jnp.where(inflation == 1.0, particles, mean + inflation * anomalies)
