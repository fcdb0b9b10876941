"""Continuous time: SDE models, Kalman-Bucy, the FPF and its gains, and the OT-FPF link."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import ot_filter as of
from ot_filter import continuous as ct
from ot_filter import reference


# --- bad input ---------------------------------------------------------------------------------


def test_bad_time_step_bandwidth_and_shapes_are_refused_by_name():
    model = ct.ornstein_uhlenbeck()
    key = jax.random.key(0)
    for dt in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="dt must be > 0"):
            ct.simulate_sde(key, model, dt, 10)
        with pytest.raises(ValueError, match="dt must be > 0"):
            ct.run_fpf(key, model, ct.constant_gain(), jnp.zeros((5, 1)), dt, 10)
    with pytest.raises(ValueError, match="epsilon must be > 0"):
        ct.kernel_gain(epsilon=0.0)
    with pytest.raises(ValueError, match=r"increments must have shape \[T >= 1, 1\]"):
        ct.run_fpf(key, model, ct.constant_gain(), jnp.zeros((5, 2)), 0.1, 10)
    bad_diffusion = model._replace(diffusion=lambda x: jnp.ones(x.shape[0] + 1))
    with pytest.raises(ValueError, match="model.diffusion must return a matrix"):
        ct.simulate_sde(key, bad_diffusion, 0.1, 10)
    bad_drift = model._replace(drift=lambda x: jnp.ones(2))
    with pytest.raises(ValueError, match="model.drift must return shape"):
        ct.run_fpf(key, bad_drift, ct.constant_gain(), jnp.zeros((5, 1)), 0.1, 10)
    with pytest.raises(ValueError, match="observation_noise_std"):
        ct.simulate_sde(key, model._replace(observation_noise_std=jnp.ones(3)), 0.1, 10)
    with pytest.raises(ValueError, match="smooth"):
        ct.learned_gain(activation="relu")
    with pytest.raises(ValueError, match="memory_limit_bytes"):
        gain = ct.kernel_gain(memory_limit_bytes=1e6)
        ct.run_fpf(key, model, gain, jnp.zeros((5, 1)), 0.1, 1000)


# --- models and the Kalman-Bucy filter -----------------------------------------------------------


def test_ornstein_uhlenbeck_simulation_has_the_stationary_variance():
    # X_0 ~ N(0, 1/2) is stationary for dX = -X dt + dB; the Euler-Maruyama chain's stationary
    # variance is dt / (1 - (1 - dt)^2) = 1 / (2 - dt). 4000 paths: s.e. of the variance 0.011.
    model = ct.ornstein_uhlenbeck(initial_std=0.5**0.5, diffusion_std=1.0)
    dt = 0.05
    keys = jax.random.split(jax.random.key(1), 4000)
    paths = jax.vmap(lambda k: ct.simulate_sde(k, model, dt, 40))(keys)
    variance = float(jnp.var(paths.states[:, -1, 0]))
    assert abs(variance - 1 / (2 - dt)) < 4 * 0.011
    assert paths.increments.shape == (4000, 40, 1) and paths.times.shape == (4000, 41)


def test_discretised_model_filtered_update_first_matches_kalman_bucy():
    # A coarse dt (0.2) makes the order of assimilation visible: increment k is generated at
    # X_{t_k}, so the EnKF must update before propagating. With 20000 particles the mean's MC s.e.
    # is sqrt(P / N) ~ 0.004; the wrong order is off by about |A m| dt ~ 0.05.
    model = ct.ornstein_uhlenbeck(observation_noise_std=0.3)
    dt = 0.2
    path = ct.simulate_sde(jax.random.key(2), model, dt, 30)
    kb = ct.kalman_bucy(model, path.increments, dt)
    discrete = ct.discretise(model, dt)
    right = of.run_filter(jax.random.key(3), discrete, of.enkf(), path.increments, 20_000,
                          save_every=0, update_first=True)
    wrong = of.run_filter(jax.random.key(3), discrete, of.enkf(), path.increments, 20_000, save_every=0)
    tolerance = 5 * float(jnp.sqrt(jnp.max(kb.cov[:, 0, 0]) / 20_000))
    assert float(jnp.max(jnp.abs(right.mean - kb.mean))) < tolerance
    assert float(jnp.max(jnp.abs(wrong.mean - kb.mean))) > 3 * tolerance


def _fpf_limit(parameters, increments, dt):
    """The N -> infinity limit of the constant-gain FPF step on a linear model: the mean and the
    variance of the particles follow this recursion exactly (the gain P H^T R^{-1} is the same
    for all particles)."""
    A, B, H, sigma, m0, P0 = parameters
    r_inv = jnp.diag(1.0 / sigma**2)

    def step(carry, dy):
        m, P = carry
        K = P @ H.T @ r_inv
        m = m + A @ m * dt + K @ (dy - H @ m * dt)
        M = jnp.eye(A.shape[0]) + A * dt - 0.5 * K @ H * dt
        P = M @ P @ M.T + B @ B.T * dt
        return (m, P), (m, jnp.diagonal(P))

    return jax.lax.scan(step, (m0, P0), increments)[1]


def test_constant_gain_fpf_matches_kalman_bucy_within_monte_carlo_error(x64):
    # Against its own mean-field limit the FPF must be unbiased with RMS errors of about one
    # Monte-Carlo s.e. (sqrt(P/N) for the mean, P sqrt(2/N) for the variance). Bounds from 64
    # independent replicates of this configuration (benchmarks/fpf_linear_convergence.py, part 4):
    # bias t-statistic spread 1.16 / 1.03 (max |t| 3.04), RMS 1.05 +- 0.12 and 0.83 +- 0.04 s.e.;
    # a 10 % gain error gives t = -8.0 +- 1.7. The limit is Kalman-Bucy up to O(dt): measured gaps
    # -0.166 dt (final variance) and at most 2.06 dt (mean RMS, 1000 paths).
    model, dt, num_particles, seeds = ct.ornstein_uhlenbeck(), 0.01, 1000, 16
    increments = ct.simulate_sde(jax.random.key(0), model, dt, 200).increments
    ref_mean, ref_var = _fpf_limit(model.parameters, increments, dt)
    result = jax.vmap(lambda k: ct.run_fpf(k, model, ct.constant_gain(), increments, dt, num_particles))(
        jax.random.split(jax.random.key(1), seeds))
    z_mean = (result.mean - ref_mean) / jnp.sqrt(ref_var / num_particles)
    z_var = (result.variance - ref_var) / (ref_var * jnp.sqrt(2.0 / num_particles))
    for z, rms_bounds in ((z_mean, (0.45, 1.65)), (z_var, (0.63, 1.03))):
        z = np.asarray(z)
        per_seed = z.mean(axis=(1, 2))
        t = per_seed.mean() / (per_seed.std(ddof=1) / np.sqrt(seeds))
        assert abs(t) < 5.0, t
        assert rms_bounds[0] < np.sqrt(np.mean(z**2)) < rms_bounds[1]
    kb = ct.kalman_bucy(model, increments, dt)
    assert abs(float(ref_var[-1, 0] - kb.cov[-1, 0, 0])) < 0.3 * dt
    assert float(jnp.sqrt(jnp.mean((ref_mean - kb.mean) ** 2))) < 2.5 * dt


# --- gains ---------------------------------------------------------------------------------------


@pytest.mark.long
def test_kernel_gain_approximates_the_exact_gain_gaussian_and_bimodal():
    # Gaussian N(0, 1), h = x: exact gain 1. Bimodal mixture, h = x: exact gain by quadrature.
    # Bounds: the errors measured at N = 1000, eps = 0.1 (benchmarks/fpf_gain_accuracy.py) are
    # about 0.12 (Gaussian) with seed-to-seed s.d. ~0.03; the bound 0.25 is 4 s.d. above.
    key = jax.random.key(4)
    x = jax.random.normal(key, (1000, 1))
    out, _, info = ct.kernel_gain(0.1).apply(None, ct.kernel_gain(0.1).init(None, x, x), x, x)
    assert bool(info.converged)
    assert float(jnp.sqrt(jnp.mean((out.gain[:, 0, 0] - 1.0) ** 2))) < 0.25

    signs = jnp.where(jax.random.bernoulli(jax.random.key(5), 0.5, (1000, 1)), 1.0, -1.0)
    mix = signs + 0.5 * jax.random.normal(jax.random.key(6), (1000, 1))
    density = reference.grid_posterior(
        lambda g: jnp.logaddexp(-2 * (g - 1) ** 2, -2 * (g + 1) ** 2), -5, 5, 4001
    )
    exact = jnp.interp(mix[:, 0], density.grid, reference.poisson_gain_1d(density, density.grid))
    gain = ct.kernel_gain(0.05, max_iterations=3000)
    out, _, info = gain.apply(None, gain.init(None, mix, mix), mix, mix)
    constant_error = float(jnp.sqrt(jnp.mean((jnp.cov(mix[:, 0]) - exact) ** 2)))
    kernel_error = float(jnp.sqrt(jnp.mean((out.gain[:, 0, 0] - exact) ** 2)))
    assert kernel_error < 0.5 * constant_error


def test_exact_quadrature_gain_is_accurate_in_both_tails():
    # Symmetric bimodal density, float32: the gain of h = x is even, that of h = x^2 odd. Integrating
    # from the left end only gave K(4) = -1.31 against K(-4) = 0.33 (asymmetry 1.6); the
    # nearer-tail integral keeps the asymmetry at float rounding (6e-6 measured).
    density = reference.grid_posterior(
        lambda g: jnp.logaddexp(-2 * (g - 1) ** 2, -2 * (g + 1) ** 2), -5.0, 5.0, 4001
    )
    inner = jnp.abs(density.grid) <= 4.0
    even = reference.poisson_gain_1d(density, density.grid)
    odd = reference.poisson_gain_1d(density, density.grid**2)
    assert float(jnp.max(jnp.abs(even - even[::-1])[inner])) < 1e-4
    assert float(jnp.max(jnp.abs(odd + odd[::-1])[inner])) < 1e-4
    # N(0, 1), h = x^2: K(x) = x exactly (trapezoid error ~7e-4 on this grid).
    gaussian = reference.grid_posterior(lambda g: -0.5 * g**2, -10.0, 10.0, 4001)
    gain = reference.poisson_gain_1d(gaussian, gaussian.grid**2)
    assert float(jnp.max(jnp.abs(gain - gaussian.grid)[jnp.abs(gaussian.grid) <= 5.0])) < 2e-3


def test_kernel_gain_is_stable_on_a_small_bimodal_ensemble():
    # dY = X^2 dt + dW with N = 200, eps = 0.1: runs where a tail particle sat across an empty
    # gap (seeds 6 and 8 of this set-up) ended in NaN or in 197 fallback steps without the
    # default damping; with it every step is finite, converged and used.
    truth = ct.squared_observation_sde(initial_mean=1.0, initial_std=1e-12)
    model = ct.squared_observation_sde()
    for seed in (6, 8):
        path = ct.simulate_sde(jax.random.key(seed), truth, 0.01, 200)
        result = ct.run_fpf(jax.random.key(100 + seed), model, ct.kernel_gain(0.1), path.increments, 0.01, 200)
        assert bool(jnp.all(jnp.isfinite(result.final_particles)))
        assert int(jnp.sum(result.info.fallback)) == 0
        assert int(jnp.sum(result.rejected_updates)) == 0
        assert float(jnp.max(jnp.abs(result.final_particles))) < 6.0


def test_fpf_rejects_a_nonfinite_update_without_poisoning_the_ensemble():
    model = ct.ornstein_uhlenbeck()
    broken = ct.function_gain(lambda x: jnp.where(x[0] > 1.0, jnp.nan, 1.0) * jnp.ones((1, 1)))
    path = ct.simulate_sde(jax.random.key(12), model, 0.01, 50)
    result = ct.run_fpf(jax.random.key(13), model, broken, path.increments, 0.01, 100)
    assert bool(jnp.all(jnp.isfinite(result.mean)))
    assert int(jnp.min(result.rejected_updates)) > 0  # N(0, 1) particles: ~16 % above 1


@pytest.mark.long
def test_learned_gain_recovers_the_exact_gains_and_falls_back_on_divergence():
    # N(0, 1): h = x has gain 1, h = x^2 has gain K(x) = x (the bimodal example's first step).
    # Measured RMS errors over |x| < 2 at N = 1000 (4 seeds, 600 and 1500 iterations, jitter 0.1
    # and 0.2): 0.04 to 0.19, mean 0.11, s.d. 0.04 (Monte-Carlo dominated: more iterations do not
    # help); bound 0.25 = mean + 3.5 s.d. The constant gain's error for h = x^2 is 0.88.
    x = jax.random.normal(jax.random.key(7), (1000, 1))
    gain = ct.learned_gain(num_iterations=600)
    for h, exact in ((x, jnp.ones(1000)), (x * x, x[:, 0])):
        out, _, info = gain.apply(jax.random.key(8), gain.init(jax.random.key(9), x, h), x, h)
        assert not bool(info.fallback)
        inner = jnp.abs(x[:, 0]) < 2  # the tails hold too few particles to pin the gain
        error = float(jnp.sqrt(jnp.mean((out.gain[inner, 0, 0] - exact[inner]) ** 2)))
        assert error < 0.25, error
    broken = ct.learned_gain(num_iterations=5, optimizer=optax.sgd(1e30))
    out, _, info = broken.apply(jax.random.key(8), broken.init(jax.random.key(9), x, x * x), x, x * x)
    assert bool(info.fallback)
    constant = float(jnp.mean((x[:, 0] - x[:, 0].mean()) * (x[:, 0] ** 2 - jnp.mean(x[:, 0] ** 2))))
    np.testing.assert_allclose(out.gain[:, 0, 0], constant, rtol=1e-5, atol=1e-6)


# --- the FPF -------------------------------------------------------------------------------------


@pytest.mark.long
def test_fpf_is_vmappable_and_skips_missing_increments():
    model = ct.ornstein_uhlenbeck(diffusion_std=0.0, rate=0.0)
    increments = jnp.full((6, 1), jnp.nan)
    result = ct.run_fpf(jax.random.key(10), model, ct.constant_gain(), increments, 0.1, 50, save_every=1)
    assert not bool(jnp.any(result.observed))
    np.testing.assert_allclose(result.particles[-1], result.particles[0], atol=0)  # nothing moves
    keys = jax.random.split(jax.random.key(11), 3)
    gain = ct.kernel_gain()
    batch = jax.vmap(lambda k: ct.run_fpf(k, model, gain, jnp.ones((4, 1)) * 0.1, 0.1, 50).mean)(keys)
    single = ct.run_fpf(keys[1], model, gain, jnp.ones((4, 1)) * 0.1, 0.1, 50).mean
    np.testing.assert_allclose(batch[1], single, rtol=1e-5, atol=1e-6)


@pytest.mark.long
def test_kernel_and_learned_gains_split_the_bimodal_posterior_the_constant_gain_cannot():
    from ot_filter.experiments.continuous_time import run_bimodal_example

    results, _ = run_bimodal_example(num_particles=300, num_steps=100, num_simulations=1,
                                     reference_particles=2000, gains=("constant", "kernel"),
                                     gain_options={"kernel": {"epsilon": 0.1}})
    gains = results["gains"]
    assert gains["kernel"]["mmd_late"]["mean"] < 0.5 * gains["constant"]["mmd_late"]["mean"]


# --- the chapter's link: OT is an exact time-discretisation of the FPF ---------------------------


def _ot_map_1d(log_prior, h, x, increment, dt):
    """The exact 1-D OT map from the prior to the posterior given one increment: the monotone
    rearrangement F_post^{-1}(F_prior(x)), by quadrature in float64."""
    grid = np.linspace(-9, 9, 400_001)
    def cdf(log_density):
        values = np.exp(log_density - log_density.max())
        cumulative = np.concatenate([[0], np.cumsum(0.5 * (values[1:] + values[:-1]))])
        return cumulative / cumulative[-1]
    prior = log_prior(grid)
    posterior = prior + h(grid) * increment - 0.5 * h(grid) ** 2 * dt
    return np.interp(np.interp(x, grid, cdf(prior)), cdf(posterior), grid)


@pytest.mark.parametrize("case", ["linear_gaussian", "bimodal"])
def test_ot_map_and_one_fpf_step_agree_to_first_order(case, x64):
    # Static state X ~ N(0, 1), dY = h(X) dt + dW. Linear-Gaussian: h = x, exact gain 1. Bimodal:
    # h = x^2 (posterior modes at +-sqrt(.)), exact gain K(x) = x. Along a path with
    # dY = h(0.8) dt + sqrt(dt) (|dW|^2 = dt), the FPF step with the exact gain (Ito form with the
    # Stratonovich correction) and the exact OT map differ by O(dt^{3/2}) while both move the
    # particles by O(dt^{1/2}): the difference relative to the move falls like dt. Without the
    # correction term the bimodal difference is only O(dt).
    h = (lambda x: x) if case == "linear_gaussian" else (lambda x: x * x)
    field = (lambda x: jnp.ones((1, 1), x.dtype)) if case == "linear_gaussian" else (lambda x: x[:, None])
    model = ct.SDEModel(jnp.zeros_like, lambda x: jnp.zeros_like(x), lambda x: h(x),
                        lambda k: jax.random.normal(k, (1,)))
    x = np.linspace(-2, 2, 41)
    if True:
        differences = {True: [], False: []}
        moves = []
        for dt in (1e-3, 1e-4):
            increment = h(0.8) * dt + np.sqrt(dt)
            ot_map = _ot_map_1d(lambda g: -0.5 * g * g, h, x, increment, dt)
            moves.append(np.max(np.abs(ot_map - x)))
            for stratonovich in (True, False):
                moved, _, _, _ = ct.fpf_step(
                    jax.random.key(0), model, ct.function_gain(field), (), jnp.asarray(x[:, None]),
                    jnp.asarray([increment]), dt, stratonovich,
                )
                differences[stratonovich].append(np.max(np.abs(np.asarray(moved[:, 0]) - ot_map)))
    corrected = np.asarray(differences[True])
    assert corrected[0] / moves[0] < 0.05  # first-order agreement already at dt = 1e-3
    assert corrected[0] / corrected[1] > 20  # O(dt^{3/2}): a factor 31.6 per decade of dt
    if case == "bimodal":
        uncorrected = np.asarray(differences[False])
        assert uncorrected[0] / uncorrected[1] < 10  # O(dt) at best without the correction
