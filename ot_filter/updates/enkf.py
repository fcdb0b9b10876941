"""Ensemble Kalman filter updates: perturbed observations and deterministic square root.

Perturbed observations (the chapter's "EnKF Bayes update", eq. Xi-EnKF-discrete-particles):

    X^i <- X^i + K (y - Y^i),   K = Cov(X, Y) Cov(Y)^{-1},   Y^i ~ h(. | X^i).

Simulation-based, the gain comes from the particle pairs (X^i, Y^i). When the model gives
additive Gaussian noise (``observation_function`` h and ``observation_noise_cov`` R), the exact
R is used instead of its sample estimate: Y^i = h(X^i) + V^i with the V^i centred, and
K = Cov(X, h) (Cov(h) + R)^{-1}. This matters for small ensembles (with N = 10 on Lorenz-63 the
purely simulated gain loses the track).

Square root (``perturbed=False``, ETKF / EnSRKF with the symmetric square root), for additive
Gaussian noise only: with anomalies A = X - mean, whitened observation anomalies
S = (h(X) - mean h) L^{-T} / sqrt(N - 1) (R = L L^T) and d = L^{-1} (y - mean h), and the thin
SVD S = U diag(s) V^T (computed through the eigen-decomposition of the smaller Gram matrix)

    mean_a = mean + A^T U diag(s / (1 + s^2)) V^T d / sqrt(N - 1)
    A_a    = (I + S S^T)^{-1/2} A = A + U diag(1 / sqrt(1 + s^2) - 1) U^T A.

Everything works on centred anomalies (N x n, N x m), never on raw second moments, so float32
is as accurate as float64; the cost is O(N m min(N, m) + N n m), linear in N. With additive
Gaussian noise, Cov(h) + R is positive definite and solved by Cholesky; the simulation-based
Cov(Y) may be singular and is solved by an eigen-decomposition with floored eigenvalues.

Multiplicative inflation scales the prior anomalies by ``inflation`` before the update.

Random rotation (``rotate=True``, DAPPER's ``rot=True``): after the update the posterior anomalies
are multiplied by a random orthogonal N x N matrix that fixes the vector of ones (so the mean and
covariance are unchanged). It spreads the analysis over all members and stops the symmetric
square root from building up outliers; on the Lorenz-63 benchmark with N = 10 it lowers the RMSE
from about 0.71 to 0.58. It draws (N - 1)^2 normals and costs O(N^2 n): meant for small ensembles
(N <= 4096).

Padded particle axis (``updates.base``): particles of log-weight -inf in the state are padding;
with k active ones, every statistic is over them only: the mean, the anomalies (exact zero rows
for padding, so padding values never enter), the covariances with divisor k - 1, the centring of
the perturbations and the ETKF's S = ... / sqrt(k - 1). Zero anomaly rows make I + S S^T block
diagonal, (I_k + S_a S_a^T) on the active block and the identity on padding, so the symmetric
square root's transform of the active block is exactly the k-particle one; the thin-SVD formulas
above are unchanged. The rotation acts on the active block only: a Haar rotation of O(k - 1) on
the complement of the k-vector of ones (Stewart's reflections beyond k - 2 are the identity).
Padding comes out at the posterior mean (zero anomaly), keeps log-weight -inf, and with
``rotate=True`` still costs O(N_max^2 n).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import masked_mean_and_anomalies
from ot_filter.lib.gaussian import cholesky_gain
from ot_filter.lib.linalg import truncated_pinv_solve
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_number
from ot_filter.lib.weights import active_mask, count_active, count_dependent
from ot_filter.model import StateSpaceModel, observation_noise_factors
from ot_filter.updates.base import BayesUpdate, UniformWeightsState, uniform_weights_init

Array = jax.Array

__all__ = ["EnKFInfo", "EnKFSettings", "enkf", "enkf_apply"]

MAX_ROTATED_PARTICLES = 4096


class EnKFInfo(NamedTuple):
    # Conditioning of the matrix the update inverts: simulation-based, max/min eigenvalue of
    # Cov(Y) (inf if singular: the pseudo-inverse then drops the null directions); exact R, the
    # squared ratio of the extreme Cholesky diagonal entries of Cov(h) + R (a cheap lower bound);
    # square root, max/min eigenvalue of I + S^T S (whitened, always finite).
    innovation_condition: Array


class EnKFSettings(NamedTuple):
    """The EnKF's numbers (traced: ``vmap`` over them runs in one program)."""

    inflation: Array  # multiplicative inflation (>= 1) of the prior anomalies


def enkf(inflation: float = 1.0, perturbed: bool = True, rotate: bool = False) -> BayesUpdate:
    """Builds the EnKF Bayes update.

    Args:
      inflation: multiplicative inflation (>= 1) of the prior anomalies; may be traced (a sweep
        over it vmaps into one compiled program).
      perturbed: True for the stochastic perturbed-observation EnKF (simulation-based);
        False for the deterministic square-root update (needs h and R in the model). Static.
      rotate: apply a random mean-preserving rotation to the posterior anomalies. Static.
    """
    settings = EnKFSettings(check_number("inflation", inflation, minimum=1.0))
    return BayesUpdate(
        uniform_weights_init,
        bind(enkf_apply, settings, perturbed=bool(perturbed), rotate=bool(rotate)),
    )


def enkf_apply(settings: EnKFSettings, key: Array, state: UniformWeightsState, particles: Array,
               observation: Array, model: StateSpaceModel, *, perturbed: bool, rotate: bool):
    """One EnKF analysis (``enkf``'s ``apply`` with its settings and structure given)."""
    if rotate and particles.shape[0] > MAX_ROTATED_PARTICLES:
        raise ValueError(
            f"enkf(rotate=True) draws (N - 1)^2 normals per update; num_particles must be "
            f"<= {MAX_ROTATED_PARTICLES}, got {particles.shape[0]}"
        )
    if not perturbed and not model.has_gaussian_observation_noise:
        raise ValueError(
            "enkf(perturbed=False) needs a model with additive Gaussian observation noise: "
            "give model.observation_function and model.observation_noise_cov"
        )
    update_key, rotation_key = jax.random.split(key)
    active = active_mask(state.log_weights)
    num_active = count_active(state.log_weights)
    mean, anomalies = masked_mean_and_anomalies(particles, active, num_active)
    # Inflation 1 leaves the particles as they are (mean + anomalies may differ by an ulp).
    inflation = settings.inflation
    anomalies = inflation * anomalies
    particles = jnp.where(inflation == 1.0, particles, mean + anomalies)
    if perturbed:
        particles, condition = _perturbed_update(
            update_key, particles, anomalies, observation, model, active, num_active
        )
    else:
        particles, condition = _square_root_update(
            mean, anomalies, observation, model, active, num_active
        )
    posterior_mean, posterior_anomalies = masked_mean_and_anomalies(particles, active, num_active)
    if rotate:
        # Active rows first (stable: the unpadded order is kept), rotated, put back.
        order = jnp.argsort((~active).astype(jnp.int32), stable=True)
        rotated = _random_rotation(rotation_key, posterior_anomalies[order], num_active)
        particles = posterior_mean + jnp.zeros_like(rotated).at[order].set(rotated)
    # Padding leaves at the posterior mean: finite and bounded, whatever it came in as.
    particles = jnp.where(active[:, None], particles, posterior_mean)
    return particles, state, EnKFInfo(condition)


def _perturbed_update(key, particles, anomalies, observation, model, active, num_active):
    """Anomalies have zero padding rows; padding rows of the result are left for the caller."""
    num_particles = particles.shape[0]
    rows = active[:, None]

    def unbiased(second_moment):  # / (k - 1)
        return count_dependent(lambda count: second_moment / (count - 1), num_active, num_particles)

    if model.has_gaussian_observation_noise:
        # Exact R: Cov(h) + R is positive definite, so Cholesky suffices (cheaper than eigh).
        predicted = jax.vmap(model.observation_function)(particles)
        noise_cov = jnp.asarray(model.observation_noise_cov, particles.dtype)
        noise_chol, _ = observation_noise_factors(model, particles.dtype)
        noise = jax.random.normal(key, predicted.shape, particles.dtype) @ noise_chol.T
        # Centred perturbations (no sampling bias), over the active particles.
        _, noise = masked_mean_and_anomalies(noise, active, num_active)
        _, predicted_anomalies = masked_mean_and_anomalies(predicted, active, num_active)
        innovation_cov = unbiased(predicted_anomalies.T @ predicted_anomalies) + noise_cov
        cross_cov = unbiased(anomalies.T @ predicted_anomalies)  # [n, m]
        innovations = jnp.where(rows, observation - predicted - noise, 0.0)  # [N, m]
        # K = Cov(X, h) (Cov(h) + R)^{-1}: solves against the n columns of Cov(X, h)^T, not the
        # N innovations. (An [m, N] right-hand side made jaxlib's CPU batched triangular solve
        # under vmap 60-150x slower for N >= 800 on 2 cores, and costs O(m^2 N) instead of O(m^2 n).)
        gain, chol = cholesky_gain(cross_cov, innovation_cov)  # [n, m]
        diagonal = jnp.diag(chol)
        condition = (jnp.max(diagonal) / jnp.min(diagonal)) ** 2  # cheap lower bound
        return particles + innovations @ gain.T, condition
    # Simulation-based: Cov(Y) is estimated and may be singular (e.g. N <= m): eigh.
    keys = jax.random.split(key, num_particles)
    simulated = jax.vmap(model.sample_observation)(keys, particles)
    _, simulated_anomalies = masked_mean_and_anomalies(simulated, active, num_active)
    innovation_cov = unbiased(simulated_anomalies.T @ simulated_anomalies)
    cross_cov = unbiased(anomalies.T @ simulated_anomalies)
    eps = jnp.finfo(particles.dtype).eps
    # Truncated pseudo-inverse: a singular Cov(Y) (N <= m, or a collapsed ensemble with a
    # deterministic simulator) updates only along the directions the ensemble spans.
    innovations = jnp.where(rows, observation - simulated, 0.0)
    solved, condition = truncated_pinv_solve(
        innovation_cov, innovations.T, relative_cutoff=observation.shape[0] * eps
    )
    return particles + (cross_cov @ solved).T, condition


def _square_root_update(mean, anomalies, observation, model, active, num_active):
    """ETKF with the symmetric square root through the smaller Gram matrix of S (see above).

    With S S^T = U diag(s2) U^T (N <= m) the transform is A + U diag(f(s2)) U^T A with
    f(s2) = 1 / sqrt(1 + s2) - 1 and the mean weights U diag(1 / (1 + s2)) U^T S d. With
    S^T S = V diag(s2) V^T (m < N), U = S V diag(s)^-1 gives A + S V diag(f(s2) / s2) V^T S^T A,
    where f(s2) / s2 = -1 / (sqrt(1 + s2) (1 + sqrt(1 + s2))) is finite at s2 = 0, and the
    mean weights S V diag(1 / (1 + s2)) V^T d. Adding the identity keeps the Gram matrix's
    squared condition number harmless: only 1 + s2 matters.

    With padding (zero rows of A, hence of S) N is the padded size in the choice of branch and
    k = ``num_active`` everywhere else; rank(S) <= k - 1.
    """
    num_particles = anomalies.shape[0]
    m = observation.shape[0]
    dtype = anomalies.dtype
    predicted = jax.vmap(model.observation_function)(mean + anomalies)
    predicted_mean, predicted_anomalies = masked_mean_and_anomalies(predicted, active, num_active)
    # Whitening matrix L^{-1} of the model's constant R (formed once per run by run_filter): the
    # whitening is then a matmul. (Triangular solves against the ensemble would become one
    # batched LAPACK solve per member under vmap, which is slower and deadlocked jaxlib's CPU
    # thread pool for vmaps over 128+ simulations on 2 cores.)
    _, whitening = observation_noise_factors(model, dtype)

    def over_scale(value):  # / sqrt(k - 1)
        return count_dependent(
            lambda count: value / jnp.sqrt(jnp.asarray(count - 1, dtype)), num_active, num_particles
        )

    whitened = over_scale(predicted_anomalies @ whitening.T)  # S [N, m]
    innovation = whitening @ (observation - predicted_mean)  # d [m]
    if num_particles <= m:
        s2, left = jnp.linalg.eigh(whitened @ whitened.T)
        s2 = jnp.clip(s2, 0.0)
        mean_weights = left @ ((left.T @ (whitened @ innovation)) / (1.0 + s2))
        shrink = 1.0 / jnp.sqrt(1.0 + s2) - 1.0
        posterior_anomalies = anomalies + left @ (shrink[:, None] * (left.T @ anomalies))
    else:
        s2, right = jnp.linalg.eigh(whitened.T @ whitened)
        s2 = jnp.clip(s2, 0.0)
        mean_weights = whitened @ (right @ ((right.T @ innovation) / (1.0 + s2)))
        root = jnp.sqrt(1.0 + s2)
        shrink_over_s2 = -1.0 / (root * (1.0 + root))
        projected = right.T @ (whitened.T @ anomalies)  # [m, n]
        posterior_anomalies = anomalies + whitened @ (right @ (shrink_over_s2[:, None] * projected))
    posterior_mean = mean + over_scale(mean_weights @ anomalies)
    # Rank of S is at most k - 1: with k - 1 < m some eigenvalues of I + S^T S are exactly 1.
    if num_particles - 1 < m:
        smallest = 1.0
    else:
        smallest = jnp.where(num_active - 1 < m, 1.0, 1.0 + jnp.min(s2))
    return posterior_mean + posterior_anomalies, (1.0 + jnp.max(s2)) / smallest


def _random_rotation(key, anomalies, num_active=None):
    """O A with O a Haar-random orthogonal matrix on the complement of the ones vector.

    With ``num_active = k`` (rows k.. are padding, zero anomalies) O is the k x k such rotation
    on the first k rows and the identity on the rest: the ones vector is that of the first k
    rows and Q is Haar on O(k - 1), the reflections k - 2.. of Stewart's product being replaced
    by the identity (all loops keep the static size N).

    The Householder reflection P (symmetric, orthogonal) maps e_1 to ones / sqrt(N), so
    O = P diag(1, Q) P with Q Haar on O(N - 1) satisfies O 1 = 1. Q is drawn by Stewart's (1980)
    algorithm, a product of N - 2 random Householder reflections and random signs, applied to
    the anomalies one reflection at a time: O(N^2 n), no N x N matrix and no LAPACK QR (a
    batched QR under vmap deadlocked jaxlib's CPU thread pool for 256 simulations).
    """
    num = anomalies.shape[0]
    dtype = anomalies.dtype
    count = num if num_active is None else num_active
    inverse_sqrt = count_dependent(lambda c: 1.0 / jnp.sqrt(c), count, num)
    ones = jnp.where(jnp.arange(num) < count, inverse_sqrt, 0.0)  # unit vector of active ones
    direction = jnp.zeros(num, dtype).at[0].set(1.0) - ones
    direction = direction / jnp.linalg.norm(direction)

    def reflect(matrix):
        return matrix - 2.0 * jnp.outer(direction, direction @ matrix)

    size = num - 1  # Q acts on rows 1..N-1 of the reflected anomalies
    gaussians_key, sign_key = jax.random.split(key)
    gaussians = jax.random.normal(gaussians_key, (size, size), dtype)
    signs = jnp.where(jax.random.bernoulli(sign_key, 0.5, (size,)), 1.0, -1.0).astype(dtype)

    block = count - 1  # Q acts on rows 1..block; padding rows beyond

    def stewart_factors(k):
        # Reflection k acts on coordinates k..block-1; its sign factor is -sign(x_k). From
        # k = block - 1 on (the last coordinate of the block, then padding) there is no
        # reflection, only the random sign.
        coordinates = jnp.arange(size)
        x = jnp.where((coordinates >= k) & (coordinates < block), gaussians[k], 0.0)
        pivot_sign = jnp.where(x[k] >= 0, 1.0, -1.0).astype(dtype)
        u = x.at[k].add(pivot_sign * jnp.linalg.norm(x))
        in_use = k < block - 1
        length = jnp.where(in_use, jnp.linalg.norm(u), 1.0)
        return jnp.where(in_use, u / length, 0.0), jnp.where(in_use, -pivot_sign, signs[k])

    ks = jnp.arange(size - 1)
    vectors, reflection_signs = jax.vmap(stewart_factors)(ks)
    diagonal = signs.at[: size - 1].set(reflection_signs)

    def apply_reflection(i, rows):
        u = vectors[size - 2 - i]  # Q = H_0 H_1 ... H_{size-2} D: apply the last one first
        return rows - 2.0 * jnp.outer(u, u @ rows)

    reflected = reflect(anomalies)
    rows = diagonal[:, None] * reflected[1:]
    rows = jax.lax.fori_loop(0, size - 1, apply_reflection, rows)
    return reflect(reflected.at[1:].set(rows))
