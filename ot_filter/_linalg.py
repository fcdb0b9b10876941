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


def weighted_mean_and_anomalies(particles: Array, weights: Array | None = None):
    """Mean ``[n]`` and centred anomalies ``[N, n]``; weights ``[N]`` sum to one (or None)."""
    if weights is None:
        mean = jnp.mean(particles, axis=0)
    else:
        mean = weights @ particles
    return mean, particles - mean


def floored_pinv_solve(matrix: Array, rhs: Array, relative_floor: float):
    """Solves ``M Z = rhs`` for symmetric PSD ``M[m, m]`` via eigh, flooring small eigenvalues.

    Eigenvalues below ``relative_floor * max eigenvalue`` are raised to that floor, so a
    singular or ill-conditioned M gives a finite (regularised) answer instead of inf/NaN.

    Returns ``(Z, condition)``: condition is max/min eigenvalue before flooring (inf if singular).
    """
    eigenvalues, eigenvectors = jnp.linalg.eigh(symmetrise(matrix))
    largest = jnp.max(eigenvalues)
    floor = jnp.maximum(relative_floor * largest, jnp.finfo(matrix.dtype).tiny)
    smallest = jnp.min(eigenvalues)
    condition = jnp.where(smallest > 0, largest / jnp.where(smallest > 0, smallest, 1.0), jnp.inf)
    inverse_eigenvalues = 1.0 / jnp.maximum(eigenvalues, floor)
    solution = eigenvectors @ (inverse_eigenvalues[:, None] * (eigenvectors.T @ rhs))
    return solution, condition
