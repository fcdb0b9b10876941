"""Small, numerically careful linear-algebra helpers shared by the filters."""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def symmetrise(matrix: Array) -> Array:
    """(M + M^T) / 2 over the last two axes."""
    return 0.5 * (matrix + jnp.swapaxes(matrix, -1, -2))


def psd_sqrt(matrix: Array) -> Array:
    """A square root L with L L^T = M for a symmetric positive SEMI-definite M (eigh-based).

    Unlike Cholesky it accepts singular matrices (e.g. noise acting on some components only).
    """
    eigenvalues, eigenvectors = jnp.linalg.eigh(symmetrise(matrix))
    return eigenvectors * jnp.sqrt(jnp.clip(eigenvalues, 0.0))


def mean_and_anomalies(particles: Array):
    """Mean ``[n]`` and centred anomalies ``[N, n]`` of equally weighted particles."""
    mean = jnp.mean(particles, axis=-2, keepdims=True)
    return mean[..., 0, :], particles - mean


def masked_mean_and_anomalies(particles: Array, active: Array, num_active: Array):
    """Mean ``[n]`` of the active rows of ``particles[N, n]`` (``active[N]`` bool, ``num_active``
    of them) and their anomalies ``[N, n]``, with exact zero rows for the inactive (padding) ones.

    Padding values never enter (``where``, not a multiplication by 0, so even inf or NaN there
    cannot leak); with every row active the values are ``mean_and_anomalies``'s.
    """
    rows = active[:, None]
    total = jnp.sum(jnp.where(rows, particles, 0.0), axis=0)
    num = particles.shape[0]
    # Nothing padded: total / num on the static num, jnp.mean's own expression (see
    # updates.base.count_dependent).
    mean = jnp.where(num_active == num, total / num, total / jnp.asarray(num_active, particles.dtype))
    return mean, jnp.where(rows, particles - mean, 0.0)


def weighted_covariance(particles: Array, log_weights: Array) -> Array:
    """Unbiased weighted covariance ``[..., n, n]`` of ``particles[..., N, n]``.

    C = sum_i w_i (x_i - mean)(x_i - mean)^T / (1 - sum_i w_i^2). When (nearly) all the mass sits
    on one particle the factor is 0 / 0; the equally weighted covariance is used instead (as
    DAPPER does), so that a collapsed ensemble still gets a usable spread estimate. Particles of
    log-weight -inf (padding, ``updates.base``) get weight 0, also in that fallback, unless
    fewer than two particles are left (then all count, to stay finite).
    """
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
    covariance = jnp.einsum("...i,...ij,...ik->...jk", weights, anomalies, anomalies)
    return covariance / (1.0 - sum_squared)


def truncated_pinv_solve(matrix: Array, rhs: Array, relative_cutoff: float):
    """Minimum-norm solution of ``M Z = rhs`` for symmetric PSD ``M[m, m]`` (pseudo-inverse).

    Eigen-directions with eigenvalue <= ``relative_cutoff * max eigenvalue`` are dropped
    (round-off there would otherwise be amplified by 1 / cutoff); M = 0 gives Z = 0.

    Returns ``(Z, condition)``: condition is max / min eigenvalue (inf if singular).
    """
    eigenvalues, eigenvectors = jnp.linalg.eigh(symmetrise(matrix))
    largest = jnp.max(eigenvalues)
    smallest = jnp.min(eigenvalues)
    kept = eigenvalues > jnp.maximum(relative_cutoff * largest, jnp.finfo(matrix.dtype).tiny)
    inverse_eigenvalues = jnp.where(kept, 1.0 / jnp.where(kept, eigenvalues, 1.0), 0.0)
    condition = jnp.where(smallest > 0, largest / jnp.where(smallest > 0, smallest, 1.0), jnp.inf)
    solution = eigenvectors @ (inverse_eigenvalues[:, None] * (eigenvectors.T @ rhs))
    return solution, condition
