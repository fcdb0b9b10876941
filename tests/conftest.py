"""Shared fixtures: random linear-Gaussian models (built in the caller's precision)."""

import os

# Before NumPy or SciPy load OpenBLAS (this file is imported first): XLA calls LAPACK (SciPy's
# OpenBLAS) from its own threads, and OpenBLAS's thread pool has crashed under concurrent callers
# (scipy#21479, #24009); the matrices here are small, so one thread costs nothing. The notebook
# kernels inherit it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402


def random_linear_gaussian(seed: int, state_dim: int = 3, observation_dim: int = 2):
    """A stable random linear-Gaussian model; matrices drawn with NumPy (float64)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(state_dim, state_dim))
    A *= 0.9 / np.max(np.abs(np.linalg.eigvals(A)))  # spectral radius 0.9
    B = rng.normal(size=(state_dim, state_dim))
    Q = 0.3 * B @ B.T / state_dim + 0.05 * np.eye(state_dim)
    H = rng.normal(size=(observation_dim, state_dim))
    C = rng.normal(size=(observation_dim, observation_dim))
    R = 0.5 * C @ C.T / observation_dim + 0.2 * np.eye(observation_dim)
    m0 = rng.normal(size=state_dim)
    D = rng.normal(size=(state_dim, state_dim))
    P0 = D @ D.T / state_dim + 0.1 * np.eye(state_dim)
    return (A, Q, H, R, m0, P0)


@pytest.fixture
def x64():
    """Runs the test body with float64 enabled."""
    with jax.enable_x64(True):
        yield
