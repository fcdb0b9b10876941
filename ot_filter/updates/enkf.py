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
from about 0.71 to 0.58. It draws N (N - 1) normals and costs O(N^2 n): meant for small ensembles
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
import numpy as np

from ot_filter.lib.ensemble import inflate, masked_mean_and_anomalies
from ot_filter.lib.gaussian import cholesky_gain
from ot_filter.lib.linalg import truncated_pinv_solve
from ot_filter.lib.static import bind
from ot_filter.lib.transform import etkf_transform
from ot_filter.lib.validation import check_number
from ot_filter.lib.weights import active_first, active_mask, count_active, count_dependent
from ot_filter.lib.validation import is_traced
from ot_filter.localisation import (
    GASPARI_COHN_HALF_WIDTH,
    Localisation,
    distances,
    taper_support,
    taper_weights,
)
from ot_filter.model import (
    StateSpaceModel,
    dense_noise_cov,
    observation_noise,
    observed_noise_factors,
    simulate_observations,
    whiten,
)
from ot_filter.updates.base import BayesUpdate, UniformWeightsState, uniform_weights_init

Array = jax.Array

__all__ = ["EnKFInfo", "EnKFSettings", "enkf", "enkf_apply"]

MAX_ROTATED_PARTICLES = 4096


class EnKFInfo(NamedTuple):
    # Conditioning of the matrix the update inverts: simulation-based, max/min eigenvalue of
    # Cov(Y) (inf if singular: the pseudo-inverse then drops the null directions); exact R, the
    # squared ratio of the extreme Cholesky diagonal entries of Cov(h) + R (a cheap lower bound);
    # square root, max/min eigenvalue of I + S^T S (whitened, always finite); rotated square
    # root, the squared ratio of the extreme diagonal entries of its Cholesky factor (a lower bound).
    innovation_condition: Array


class EnKFSettings(NamedTuple):
    """The EnKF's numbers (traced: ``vmap`` over them runs in one program)."""

    inflation: Array  # multiplicative inflation (>= 1) of the prior anomalies
    localisation: Localisation | None = None  # Schur-product localisation (perturbed only)


def enkf(inflation: float = 1.0, perturbed: bool = True, rotate: bool = False,
         localisation: Localisation | None = None) -> BayesUpdate:
    """Builds the EnKF Bayes update.

    Args:
      inflation: multiplicative inflation (>= 1) of the prior anomalies; may be traced (a sweep
        over it vmaps into one compiled program).
      perturbed: True for the stochastic perturbed-observation EnKF (simulation-based);
        False for the deterministic square-root update (needs h and R in the model). Static.
      rotate: apply a random mean-preserving rotation to the posterior anomalies. Static.
      localisation: optional ``ot_filter.localisation(model.geometry, radius)``: Schur-product
        (covariance) localisation of the perturbed EnKF, Cov(X, Y) and Cov(Y) multiplied
        entrywise by the taper of the distances (dense: O(n m + m^2) memory, for m up to a few
        thousand). The square-root EnKF localises as ``ot_filter.letkf``.
    """
    if localisation is not None:
        if not isinstance(localisation, Localisation):
            raise TypeError(f"localisation must be built by ot_filter.localisation(...), got "
                            f"{type(localisation).__name__}")
        if not perturbed:
            raise ValueError("enkf(perturbed=False) does not localise: use ot_filter.letkf "
                             "(the local square-root filter) or enkf(perturbed=True, localisation=...)")
        if localisation.taper != "gaspari_cohn":
            # A Schur product keeps Cov(Y) positive semi-definite only with a positive-definite
            # taper matrix: the step function's is indefinite (on a 40-site ring at radius 4, its
            # smallest eigenvalue is -1.96), and Cholesky would fail.
            raise ValueError("enkf(localisation=...) needs taper='gaspari_cohn' (the step taper's "
                             "matrix is indefinite); letkf takes either")
        _check_schur_support(localisation)
    settings = EnKFSettings(check_number("inflation", inflation, minimum=1.0), localisation)
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
    if settings.localisation is not None:
        geometry = settings.localisation.geometry
        sizes = (geometry.state_positions.shape[0], geometry.observation_positions.shape[0])
        if sizes != (particles.shape[1], observation.shape[0]):
            raise ValueError(f"the localisation places {sizes[0]} state coordinates and {sizes[1]} "
                             f"observations; the particles have {particles.shape[1]} and the "
                             f"observation {observation.shape[0]}: build it from this model's geometry")
    update_key, rotation_key = jax.random.split(key)
    active = active_mask(state.log_weights)
    num_active = count_active(state.log_weights)
    mean, anomalies = masked_mean_and_anomalies(particles, active, num_active)
    particles = inflate(particles, active, settings.inflation, (mean, anomalies))
    anomalies = settings.inflation * anomalies
    if not perturbed and rotate:
        # Rotated square root: a Cholesky root on the complement of the ones vector instead of
        # the symmetric root (no eigen-decomposition; the same ensemble in law, see there).
        posterior_mean, posterior_anomalies, condition = _rotated_square_root_update(
            rotation_key, mean, anomalies, observation, model, active, num_active
        )
        particles = jnp.where(active[:, None], posterior_mean + posterior_anomalies, posterior_mean)
        return particles, state, EnKFInfo(condition)
    if perturbed:
        particles, condition = _perturbed_update(
            update_key, particles, anomalies, observation, model, active, num_active,
            settings.localisation,
        )
    else:
        particles, condition = _square_root_update(
            mean, anomalies, observation, model, active, num_active
        )
    posterior_mean, posterior_anomalies = masked_mean_and_anomalies(particles, active, num_active)
    if rotate:
        # Active rows first (stable: the unpadded order is kept), rotated, put back.
        order = active_first(active)
        rotated = random_rotation(rotation_key, posterior_anomalies[order], num_active)
        particles = posterior_mean + jnp.zeros_like(rotated).at[order].set(rotated)
    # Padding leaves at the posterior mean: finite and bounded, whatever it came in as.
    particles = jnp.where(active[:, None], particles, posterior_mean)
    return particles, state, EnKFInfo(condition)


def _perturbed_update(key, particles, anomalies, observation, model, active, num_active,
                      localisation):
    """Anomalies have zero padding rows; padding rows of the result are left for the caller.

    Missing components (NaN in the observation) get zero rows and columns in the gain's
    equations (identity rows in Cov(h) + R, dropped directions of the simulated Cov(Y)): the
    result is that of the model with those rows of h and R deleted."""
    num_particles = particles.shape[0]
    rows = active[:, None]
    observed = jnp.isfinite(observation)
    both_observed = observed[:, None] & observed[None, :]

    def unbiased(second_moment):  # / (k - 1)
        return count_dependent(lambda count: second_moment / (count - 1), num_active, num_particles)

    state_taper, observation_taper = _schur_tapers(localisation, particles.dtype)
    if model.has_gaussian_observation_noise:
        # Exact R: Cov(h) + R is positive definite, so Cholesky suffices (cheaper than eigh).
        predicted = jax.vmap(model.observation_function)(particles)
        noise_cov = dense_noise_cov(model.observation_noise_cov).astype(particles.dtype)
        # Draws of N(0, R); on the observed components, draws of N(0, R_oo) (a marginal; that
        # deleting components keeps the others' draws: tests/test_partial_observations.py).
        noise = observation_noise(key, model, num_particles, predicted.shape[1], particles.dtype)
        # Centred perturbations (no sampling bias), over the active particles.
        _, noise = masked_mean_and_anomalies(noise, active, num_active)
        _, predicted_anomalies = masked_mean_and_anomalies(predicted, active, num_active)
        innovation_cov = observation_taper * unbiased(predicted_anomalies.T @ predicted_anomalies)
        innovation_cov = jnp.where(both_observed, innovation_cov + noise_cov,
                                   jnp.eye(observation.shape[0], dtype=particles.dtype))
        cross_cov = state_taper * unbiased(anomalies.T @ predicted_anomalies)  # [n, m]
        cross_cov = jnp.where(observed[None, :], cross_cov, 0.0)
        innovations = jnp.where(rows & observed, observation - predicted - noise, 0.0)  # [N, m]
        # K = Cov(X, h) (Cov(h) + R)^{-1}: solves against the n columns of Cov(X, h)^T, not the
        # N innovations. (An [m, N] right-hand side made jaxlib's CPU batched triangular solve
        # under vmap 60-150x slower for N >= 800 on 2 cores, and costs O(m^2 N) instead of O(m^2 n).)
        gain, chol = cholesky_gain(cross_cov, innovation_cov)  # [n, m]
        diagonal = jnp.diag(chol)
        condition = (jnp.max(diagonal) / jnp.min(diagonal)) ** 2  # cheap lower bound
        return particles + innovations @ gain.T, condition
    # Simulation-based: Cov(Y) is estimated and may be singular (e.g. N <= m): eigh.
    simulated = simulate_observations(key, model, particles)  # a key per particle: no h and R here
    _, simulated_anomalies = masked_mean_and_anomalies(simulated, active, num_active)
    simulated_anomalies = jnp.where(observed, simulated_anomalies, 0.0)
    innovation_cov = observation_taper * unbiased(simulated_anomalies.T @ simulated_anomalies)
    cross_cov = state_taper * unbiased(anomalies.T @ simulated_anomalies)
    eps = jnp.finfo(particles.dtype).eps
    # Truncated pseudo-inverse: a singular Cov(Y) (N <= m, or a collapsed ensemble with a
    # deterministic simulator) updates only along the directions the ensemble spans.
    innovations = jnp.where(rows & observed, observation - simulated, 0.0)
    solved, condition = truncated_pinv_solve(
        innovation_cov, innovations.T, relative_cutoff=observation.shape[0] * eps
    )
    return particles + (cross_cov @ solved).T, condition


def _check_schur_support(localisation):
    """Gaspari-Cohn is positive definite in Euclidean space, but on a periodic axis only while its
    support (2 c) stays within half the period (on a 40-site ring its matrix's smallest
    eigenvalue is -0.05 at radius 8 and -0.74 at radius 12); a concrete radius is checked."""
    if is_traced(localisation.radius):
        return
    period = np.asarray(localisation.geometry.period, dtype=float)
    support = taper_support(float(localisation.radius), localisation.taper)
    if np.any(np.isfinite(period) & (support > period / 2)):
        raise ValueError(
            f"the Gaspari-Cohn support 2 c = {support:.3g} exceeds half the period "
            f"{period.min() / 2:.3g}: its Schur product is then not positive definite; use a "
            f"smaller radius (at most {period.min() / (4 * GASPARI_COHN_HALF_WIDTH):.3g}) or letkf")


def _schur_tapers(localisation, dtype):
    """``(rho_xy [n, m], rho_yy [m, m])`` of the Schur-product localisation, or ``(1, 1)``."""
    if localisation is None:
        return 1.0, 1.0
    geometry = localisation.geometry

    def taper(a, b):
        return taper_weights(distances(geometry, a, b), localisation.radius, localisation.taper)

    observations = geometry.observation_positions
    return (taper(geometry.state_positions, observations).astype(dtype),
            taper(observations, observations).astype(dtype))


def whitened_observations(mean, anomalies, observation, model, active, num_active):
    """``(S [N, m], d [m], over_scale)`` of the square-root updates: the whitened observation
    anomalies S = (h(X) - mean h) L^{-1} / sqrt(k - 1), the whitened innovation d and the
    division by sqrt(k - 1). Missing components (NaN) are zero columns of S and d, whitened with
    the factor of R_oo (``observed_noise_factors``)."""
    num_particles = anomalies.shape[0]
    dtype = anomalies.dtype
    predicted = jax.vmap(model.observation_function)(mean + anomalies)
    predicted_mean, predicted_anomalies = masked_mean_and_anomalies(predicted, active, num_active)
    # Whitening by L^{-1} of the model's constant R (formed once per run by run_filter): a
    # matmul. (Triangular solves against the ensemble would become one batched LAPACK solve per
    # member under vmap, which is slower and deadlocked jaxlib's CPU thread pool for vmaps over
    # 128+ simulations on 2 cores.)
    observed = jnp.isfinite(observation)
    factors = observed_noise_factors(model, observed, dtype)

    def over_scale(value):  # / sqrt(k - 1)
        return count_dependent(
            lambda count: value / jnp.sqrt(jnp.asarray(count - 1, dtype)), num_active, num_particles
        )

    whitened = over_scale(jnp.where(observed, whiten(factors, predicted_anomalies), 0.0))  # S
    residual = jnp.where(observed, observation - predicted_mean, 0.0)
    innovation = jnp.where(observed, whiten(factors, residual), 0.0)  # d [m]
    return whitened, innovation, over_scale


def _square_root_update(mean, anomalies, observation, model, active, num_active):
    """ETKF with the symmetric square root (``lib.transform.etkf_transform``).

    With padding (zero rows of A, hence of S) N is the padded size in the choice of branch and
    k = ``num_active`` everywhere else; rank(S) <= k - 1. Missing components (NaN) are zero
    columns of S and d, whitened with the factor of R_oo (``observed_noise_factors``): the
    result is that of the model with those rows deleted.
    """
    num_particles = anomalies.shape[0]
    m = observation.shape[0]
    observed = jnp.isfinite(observation)
    whitened, innovation, over_scale = whitened_observations(
        mean, anomalies, observation, model, active, num_active
    )
    mean_weights, posterior_anomalies, s2 = etkf_transform(whitened, innovation, anomalies)
    posterior_mean = mean + over_scale(mean_weights @ anomalies)
    # Rank of S is at most min(k - 1, number observed): other eigenvalues of I + S^T S are 1.
    if num_particles - 1 < m:
        smallest = 1.0
    else:
        smallest = jnp.where((num_active - 1 < m) | ~jnp.all(observed), 1.0, 1.0 + jnp.min(s2))
    return posterior_mean + posterior_anomalies, (1.0 + jnp.max(s2)) / smallest


def _rotated_square_root_update(key, mean, anomalies, observation, model, active, num_active):
    """Square root followed by the random rotation, without an eigen-decomposition.

    ``(posterior mean [n], posterior anomalies [N, n] (zero padding rows), condition)``. S has
    zero column sums over the active rows, so in the basis of the reflection P of
    ``random_rotation`` (active rows first) P (I + S S^T) P = diag(1, I + S' S'^T) with
    S' = (P S)[1:]. With the Cholesky factor L L^T = I + S' S'^T, T = P diag(1, L^{-1}) P is a
    square root of (I + S S^T)^{-1} (T^T T = (I + S S^T)^{-1}) that fixes the ones vector, so
    T A has the posterior mean and covariance of the symmetric root T_s A. T = V T_s with
    V = T T_s^{-1} orthogonal and fixing ones; for O Haar on the complement of ones, O V is again
    Haar, so the rotated O T A has the law of the rotated symmetric root O T_s A: the same
    analysis ensemble in distribution (not draw by draw). The mean increment
    (S d)^T (I + S S^T)^{-1} A / sqrt(k - 1) is z^T Z / sqrt(k - 1) with
    [Z | z] = L^{-1} [(P A)[1:] | S' d]. One (N - 1) x (N - 1) Cholesky and one triangular solve
    (with the rotation's, two): jaxlib's CPU eigh of a 24 x 24 matrix alone was half a
    Lorenz-96 cycle (~43 of 87 us).

    ``condition`` is the squared ratio of the extreme diagonal entries of L, a cheap lower bound
    on the max / min eigenvalue of I + S^T S (as the perturbed EnKF's exact-R branch reports).
    """
    num_particles = anomalies.shape[0]
    dtype = anomalies.dtype
    whitened, innovation, over_scale = whitened_observations(
        mean, anomalies, observation, model, active, num_active
    )
    order = active_first(active)
    reflect = _ones_reflection(num_particles, num_active, dtype)
    reflected_anomalies = reflect(anomalies[order])[1:]  # (P A)[1:], padding rows 0
    reflected_whitened = reflect(whitened[order])[1:]  # S', padding rows 0
    gram = jnp.eye(num_particles - 1, dtype=dtype) + reflected_whitened @ reflected_whitened.T
    chol = jnp.linalg.cholesky(gram)
    right = jnp.concatenate([reflected_anomalies, (reflected_whitened @ innovation)[:, None]], axis=1)
    solved = jax.scipy.linalg.solve_triangular(chol, right, lower=True)
    transformed, weights = solved[:, :-1], solved[:, -1]
    posterior_mean = mean + over_scale(weights @ transformed)
    rotated = _haar_rotate(key, transformed, num_active - 1)
    full = reflect(jnp.concatenate([jnp.zeros_like(anomalies[:1]), rotated]))
    posterior_anomalies = jnp.zeros_like(full).at[order].set(full)  # back to the original row order
    diagonal = jnp.diag(chol)
    return posterior_mean, posterior_anomalies, (jnp.max(diagonal) / jnp.min(diagonal)) ** 2


def _ones_reflection(num, count, dtype):
    """``reflect(M) = P M`` with P the Householder reflection (symmetric, orthogonal) that maps
    e_1 to the unit vector of ones on the first ``count`` of ``num`` rows (identity beyond)."""
    # In the particles' dtype: an int count would make the ones vector float32 under x64.
    inverse_sqrt = count_dependent(lambda c: 1.0 / jnp.sqrt(jnp.asarray(c, dtype)), count, num)
    ones = jnp.where(jnp.arange(num) < count, inverse_sqrt, 0.0)  # unit vector of active ones
    direction = jnp.zeros(num, dtype).at[0].set(1.0) - ones
    direction = direction / jnp.linalg.norm(direction)

    def reflect(matrix):
        return matrix - 2.0 * jnp.outer(direction, direction @ matrix)

    return reflect


def _haar_rotate(key, rows, block):
    """Q @ rows for ``rows[size, n]``, Q Haar on O(block) on the first ``block`` rows and the
    identity on the rest (``block`` may be traced, 1 <= block <= size).

    Stewart's (1980) algorithm: Q = H_0 H_1 ... H_{size-2} D, random Householder reflections
    (reflection k acts on coordinates k..block-1; none from k = block - 1 on) and random signs.
    The product is applied at once in the compact WY form H_0 ... H_{K-1} = I - U T^{-1} U^T,
    T = I / 2 + striu(U^T U) (unit u_k; a zero u_k is the identity): a few matrix products and
    one K x K triangular solve instead of K sequential rank-one updates (each a handful of XLA
    CPU runtime ops). One normal draw of [size, size + 1] gives the Gaussians and, by the signs
    of its last column, the random signs (one Threefry call instead of three).
    """
    size = rows.shape[0]
    dtype = rows.dtype
    draws = jax.random.normal(key, (size, size + 1), dtype)
    gaussians = draws[:, :size]
    # Random signs on the block only: rows beyond it (padding) keep the identity.
    signs = jnp.where((draws[:, size] >= 0) | (jnp.arange(size) >= block), 1.0, -1.0).astype(dtype)
    if size == 1:  # O(1): a random sign
        return signs[:, None] * rows

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

    vectors, reflection_signs = jax.vmap(stewart_factors)(jnp.arange(size - 1))  # [K, size]
    diagonal = signs.at[: size - 1].set(reflection_signs)
    rows = diagonal[:, None] * rows
    inverse_t = 0.5 * jnp.eye(size - 1, dtype=dtype) + jnp.triu(vectors @ vectors.T, 1)
    coefficients = jax.scipy.linalg.solve_triangular(inverse_t, vectors @ rows, lower=False)
    return rows - vectors.T @ coefficients


def random_rotation(key, anomalies, num_active=None):
    """O A with O a Haar-random orthogonal matrix on the complement of the ones vector.

    With ``num_active = k`` (rows k.. are padding, zero anomalies) O is the k x k such rotation
    on the first k rows and the identity on the rest: the ones vector is that of the first k
    rows and Q is Haar on O(k - 1) (all shapes keep the static size N).

    The Householder reflection P (symmetric, orthogonal) maps e_1 to ones / sqrt(k), so
    O = P diag(1, Q) P with Q Haar on O(k - 1) satisfies O 1 = 1. Q is Stewart's product of
    random reflections (``_haar_rotate``): O(N^2 n), no LAPACK QR (a batched QR under vmap
    deadlocked jaxlib's CPU thread pool for 256 simulations).
    """
    num = anomalies.shape[0]
    count = num if num_active is None else num_active
    reflect = _ones_reflection(num, count, anomalies.dtype)
    reflected = reflect(anomalies)
    rows = _haar_rotate(key, reflected[1:], count - 1)
    return reflect(reflected.at[1:].set(rows))
