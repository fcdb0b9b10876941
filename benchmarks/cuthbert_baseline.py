"""cuthbert baseline for the Lorenz-63 twin experiment (speed and rmse.a), next to ot_filter's.

Run with an interpreter that has cuthbert installed (not ot_filter's), e.g.

    /work/cuthbert-venv/bin/python benchmarks/cuthbert_baseline.py --data truths.npz

This script imports neither ot_filter nor DAPPER: it only calls cuthbert's public API
(``cuthbert.smc.particle_filter.build_filter``, ``cuthbert.ensemble_kalman.
ensemble_kalman_filter.build_filter``, ``cuthbert.filter``, ``cuthbertlib.resampling``). The
ot_filter-side numbers (N, inflation, jitter, ESS threshold, burn-in) default to those of
``ot_filter/experiments/twin_configurations.py``, which it loads by file path (that file imports
neither ot_filter nor JAX at import time).

Data (``--data``): a .npz with ``observations [S, T, 3]`` and ``states [S, T, 3]``: S truths of
Lorenz-63 as ``ot_filter.simulate(key, ot_filter.models.lorenz63(), T)`` draws them, i.e.
X_0 ~ N(x0, 2 I), then for t = 1..T: X_t = 25 RK4 steps of dt = 0.01 from X_{t-1} (no process
noise), Y_t = X_t + N(0, 2 I). ``states[:, t - 1]`` is X_t (X_0 is not stored). This is the
convention of cuthbert's filters too: the initial state carries no observation and
``cuthbert.filter`` returns T + 1 states, the first being the prior; it is dropped here.

Model (copied from ``ot_filter.models.lorenz63()``'s defaults, DAPPER's Lorenz63.sakov2012):
sigma 10, rho 28, beta 8/3, dt 0.01, RK4, 25 steps per observation, all 3 components observed
with noise std sqrt(2), initial N((1.509, -1.531, 25.46), 2 I), no process noise.

Configurations (``--configs``; N from ``--particles`` / ``--ensemble``):

    L63/PartFilt-N800     cuthbert.smc.particle_filter (bootstrap: propagate_sample = the model,
                          log_potential = the Gaussian observation log-density), resampling_fn =
                          ess_decorator(regularised systematic, --ess-threshold 0.2).
                          "Regularised systematic" = cuthbertlib.resampling.systematic.resampling
                          followed by ot_filter's / DAPPER's regularisation jitter (ot_filter
                          sir(jitter=0.9), DAPPER PartFilt(reg=0.9)): after each resampling every
                          particle gets N(0, (jitter N^(-1/(n+4)))^2 C_w) noise, C_w the unbiased
                          weighted covariance of the ensemble before resampling (the equally
                          weighted one if one particle holds all the mass). It is passed as the
                          filter's ``resampling_fn`` (cuthbert's documented extension point), so
                          the model itself keeps no process noise (``--process-noise`` can add
                          some, default 0).
    L63/EnKF-PertObs-N10  cuthbert.ensemble_kalman.ensemble_kalman_filter, perturbed_obs=True,
                          inflation 0.02 (cuthbert's multiplier is 1 + inflation on the forecast
                          anomalies, i.e. ot_filter's enkf(inflation=1.02)).
    L63/EnKF-Det-N10      (not run by default) the same with perturbed_obs=False: cuthbert then
                          moves every member by K (y - h(x_i)) with the unperturbed y, which is
                          NOT a square-root EnKF (the analysis spread shrinks by (I - K H), not
                          (I - K H)^(1/2)); cuthbert has no ETKF / EAKF / square-root EnKF.

What is measured, per seed s (filter key fold_in(key(--filter-seed), s)):

- ``seconds``: median over ``--repeats`` calls of the wall time (``time.perf_counter``) of one
  jitted twin experiment: the whole filter over T observations and its rmse.a,
  ``block_until_ready``. ``--api offline`` (default) runs ``cuthbert.filter`` (a ``lax.scan``
  that stacks every filter state, particles included, [T + 1, N, 3]); ``--api online`` scans
  ``filter_prepare`` / ``filter_combine`` itself and keeps only the mean (like ot_filter's
  ``save_every=0``).
- ``compile_s``: (first call) - (median steady call) on the first seed: tracing, lowering, XLA
  compilation and, for the particle filter on CPU, numba's compilation of cuthbert's inverse-CDF
  callback.
- ``resample_fraction`` (particle filter only): fraction of the T filter steps that began by
  resampling (cuthbert resamples lazily, at the start of the next step, on the previous weights).
- ``rmse_a``: mean over analysis times k >= ``--first-averaged`` (default 64: DAPPER's BurnIn 16
  at dt_obs 0.25, as in benchmarks/lorenz_twin.py) of sqrt(mean_i (mu_i - x_i)^2), mu the filter
  mean (weighted by the particle weights for the particle filter).

Output: one JSON object on stdout ``{config: {"seconds": [...], "compile_s": ..., "rmse_a":
[...], ...}, "_meta": {...}}``, one list entry per seed; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import jax

if "--x64" in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import cuthbert  # noqa: E402
from cuthbert.ensemble_kalman import ensemble_kalman_filter  # noqa: E402
from cuthbert.smc import particle_filter  # noqa: E402
from cuthbertlib.resampling import ess_decorator, systematic  # noqa: E402




from twin_configurations_by_path import load_twin_configurations  # noqa: E402

_TWIN = load_twin_configurations()
PARTICLE_FILTER = _TWIN.TWIN_CONFIGURATIONS["L63/PartFilt-N800"]  # N 800, jitter 0.9, ESS 0.2
ENKF = _TWIN.TWIN_CONFIGURATIONS["L63/EnKF-PertObs-N10"]  # N 10, inflation 1.02
FIRST_AVERAGED = _TWIN.TWIN_EXPERIMENTS["lorenz63"].burn_in  # 64: DAPPER's BurnIn 16 at dt_obs 0.25

# ---- Lorenz-63, ot_filter.models.lorenz63() defaults (Sakov et al. 2012, as in DAPPER) ----
SIGMA, RHO, BETA = 10.0, 28.0, 8.0 / 3.0
DT = 0.01
STEPS_PER_OBSERVATION = 25
OBSERVATION_STD = 2.0**0.5
INITIAL_MEAN = (1.509, -1.531, 25.46)
INITIAL_STD = 2.0**0.5
DIM = 3


def vector_field(x):
    return jnp.stack(
        [SIGMA * (x[1] - x[0]), x[0] * (RHO - x[2]) - x[1], x[0] * x[1] - BETA * x[2]]
    )


def rk4_step(x):
    k1 = vector_field(x)
    k2 = vector_field(x + 0.5 * DT * k1)
    k3 = vector_field(x + 0.5 * DT * k2)
    k4 = vector_field(x + DT * k3)
    return x + (DT / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def make_transition(process_noise_std: float):
    """x_{t-1} -> x_t: 25 RK4 steps (plus N(0, std^2 I) after each step if std > 0)."""

    def transition(key, x):
        if process_noise_std == 0.0:
            return jax.lax.fori_loop(0, STEPS_PER_OBSERVATION, lambda _, x: rk4_step(x), x)

        def noisy_step(i, x):
            noise = jax.random.normal(jax.random.fold_in(key, i), x.shape, x.dtype)
            return rk4_step(x) + process_noise_std * noise

        return jax.lax.fori_loop(0, STEPS_PER_OBSERVATION, noisy_step, x)

    return transition


def init_sample(key):
    mean = jnp.asarray(INITIAL_MEAN, dtype=jnp.zeros(()).dtype)
    return mean + INITIAL_STD * jax.random.normal(key, (DIM,), mean.dtype)


def observation_log_density(y, x):
    residual = (y - x) / OBSERVATION_STD
    return -0.5 * jnp.sum(residual**2) - DIM * (
        jnp.log(OBSERVATION_STD) + 0.5 * jnp.log(2.0 * jnp.pi)
    )


# ---- particle filter -------------------------------------------------------------------------


def weighted_covariance(particles, log_weights):
    """Unbiased weighted covariance; equally weighted when one particle holds all the mass
    (ot_filter.lib.ensemble.weighted_covariance without padding)."""
    weights = jax.nn.softmax(log_weights)
    eps = jnp.finfo(particles.dtype).eps
    collapsed = 1.0 - jnp.max(weights) < 100 * eps
    weights = jnp.where(collapsed, 1.0 / weights.shape[0], weights)
    mean = weights @ particles
    anomalies = particles - mean
    covariance = jnp.einsum("i,ij,ik->jk", weights, anomalies, anomalies)
    return covariance / (1.0 - jnp.sum(weights**2))


def psd_sqrt(matrix):
    eigenvalues, eigenvectors = jnp.linalg.eigh(0.5 * (matrix + matrix.T))
    return eigenvectors * jnp.sqrt(jnp.clip(eigenvalues, 0.0))


def regularised_systematic(jitter: float):
    """cuthbert Resampling: systematic resampling, then ot_filter's sir(jitter) noise."""

    def resampling(key, logits, positions, n):
        resample_key, jitter_key = jax.random.split(key)
        indices, logits_out, resampled = systematic.resampling(resample_key, logits, positions, n)
        if jitter > 0.0:
            scale = jitter * n ** (-1.0 / (DIM + 4))
            root = psd_sqrt(weighted_covariance(positions, logits))
            noise = jax.random.normal(jitter_key, resampled.shape, resampled.dtype)
            resampled = resampled + scale * noise @ root.T
        return indices, logits_out, resampled

    return resampling


def build_particle_filter(num_particles, ess_threshold, jitter, process_noise_std):
    transition = make_transition(process_noise_std)
    resampling = regularised_systematic(jitter)
    if ess_threshold < 1.0:
        resampling = ess_decorator(resampling, ess_threshold)
    filter_obj = particle_filter.build_filter(
        init_sample=init_sample,
        propagate_sample=lambda key, x, y: transition(key, x),
        log_potential=lambda x_prev, x, y: observation_log_density(y, x),
        n_filter_particles=num_particles,
        resampling_fn=resampling,
    )

    def mean(state):  # weighted mean of the (not yet resampled) particles
        return jax.nn.softmax(state.log_weights, axis=-1)[..., None, :] @ state.particles

    def resampled(state):  # did this step start with a resampling? (ancestors != identity)
        return jnp.any(state.ancestor_indices != jnp.arange(num_particles), axis=-1)

    return filter_obj, lambda state: mean(state)[..., 0, :], resampled


# ---- ensemble Kalman filter ------------------------------------------------------------------


def build_enkf(num_particles, inflation, perturbed, process_noise_std):
    transition = make_transition(process_noise_std)

    def get_dynamics(y):
        return lambda x, key: transition(key, x)

    def get_observations(y):
        chol_R = OBSERVATION_STD * jnp.eye(DIM, dtype=y.dtype)
        return (lambda x: x), chol_R, y

    filter_obj = ensemble_kalman_filter.build_filter(
        init_sample=init_sample,
        get_dynamics=get_dynamics,
        get_observations=get_observations,
        n_particles=num_particles,
        inflation=inflation,
        perturbed_obs=perturbed,
    )
    return filter_obj, lambda state: jnp.mean(state.ensemble, axis=-2), None


# ---- twin experiment -------------------------------------------------------------------------


def make_twin(filter_obj, mean_fn, resampled_fn, api: str, first_averaged: int):
    """jitted ``twin(key, observations[T, 3], states[T, 3]) -> (rmse_a, resample_fraction)``
    (the fraction of the T steps that began with a resampling; NaN for the EnKF)."""
    if resampled_fn is None:
        resampled_fn = lambda state: jnp.full(state.ensemble.shape[:-2], jnp.nan)  # noqa: E731

    def twin(key, observations, states):
        init_key, filter_key = jax.random.split(key)
        init_state = filter_obj.init_prepare(key=init_key)
        if api == "offline":
            filtered = cuthbert.filter(filter_obj, observations, init_state, key=filter_key)
            means = mean_fn(filtered)[1:]  # drop the prior (time 0)
            resampled = resampled_fn(filtered)[1:]
        else:
            init_state = init_state._replace(model_inputs=jnp.zeros_like(observations[0]))
            keys = jax.random.split(filter_key, observations.shape[0])

            def body(state, inputs):
                y, k = inputs
                state = filter_obj.filter_combine(state, filter_obj.filter_prepare(y, key=k))
                return state, (mean_fn(state), resampled_fn(state))

            _, (means, resampled) = jax.lax.scan(body, init_state, (observations, keys))
        errors = jnp.sqrt(jnp.mean((means - states) ** 2, axis=-1))
        return jnp.mean(errors[first_averaged:]), jnp.mean(resampled.astype(errors.dtype))

    return jax.jit(twin)


def time_call(fn, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - start, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help=".npz with observations/states [S, T, 3]")
    parser.add_argument("--configs", default="PartFilt,EnKF-PertObs",
                        help="comma-separated: PartFilt, EnKF-PertObs, EnKF-Det")
    parser.add_argument("--particles", type=int, default=PARTICLE_FILTER.num_particles,
                        help="particle filter N")
    parser.add_argument("--ensemble", type=int, default=ENKF.num_particles, help="EnKF N")
    parser.add_argument("--jitter", type=float, default=PARTICLE_FILTER.settings["jitter"],
                        help="regularisation after resampling (ot_filter sir jitter, DAPPER reg)")
    parser.add_argument("--ess-threshold", type=float,
                        default=PARTICLE_FILTER.settings["ess_threshold"],
                        help="resample when ESS < threshold N (DAPPER NER); >= 1: every step")
    parser.add_argument("--process-noise", type=float, default=0.0,
                        help="filter-model process noise std per RK4 step (default 0)")
    parser.add_argument("--inflation", type=float, default=ENKF.settings["inflation"],
                        help="EnKF multiplicative inflation (ot_filter/DAPPER convention)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=0, help="use the first S seeds (0: all)")
    parser.add_argument("--filter-seed", type=int, default=1)
    parser.add_argument("--first-averaged", type=int, default=FIRST_AVERAGED)
    parser.add_argument("--api", choices=("offline", "online"), default="offline")
    parser.add_argument("--x64", action="store_true", help="jax_enable_x64 (default float32)")
    args = parser.parse_args()

    data = np.load(args.data)
    observations_all = np.asarray(data["observations"])
    states_all = np.asarray(data["states"])
    if observations_all.ndim == 2:
        observations_all, states_all = observations_all[None], states_all[None]
    if observations_all.shape != states_all.shape or observations_all.shape[-1] != DIM:
        parser.error(f"observations {observations_all.shape} / states {states_all.shape}: "
                     "need equal shapes [S, T, 3]")
    num_seeds, num_obs = observations_all.shape[:2]
    if args.seeds:
        num_seeds = min(num_seeds, args.seeds)
    if num_obs <= args.first_averaged:
        parser.error(f"T = {num_obs} <= --first-averaged {args.first_averaged}")
    dtype = jnp.zeros(()).dtype

    builders = {
        "PartFilt": (f"L63/PartFilt-N{args.particles}", lambda: build_particle_filter(
            args.particles, args.ess_threshold, args.jitter, args.process_noise)),
        "EnKF-PertObs": (f"L63/EnKF-PertObs-N{args.ensemble}", lambda: build_enkf(
            args.ensemble, args.inflation - 1.0, True, args.process_noise)),
        "EnKF-Det": (f"L63/EnKF-Det-N{args.ensemble}", lambda: build_enkf(
            args.ensemble, args.inflation - 1.0, False, args.process_noise)),
    }
    results = {}
    for short in [c.strip() for c in args.configs.split(",") if c.strip()]:
        if short not in builders:
            parser.error(f"unknown config {short!r}; choose from {sorted(builders)}")
        name, build = builders[short]
        twin = make_twin(*build(), args.api, args.first_averaged)
        entry = {"seconds": [], "compile_s": None, "rmse_a": [], "seeds": []}
        base_key = jax.random.key(args.filter_seed)
        for s in range(num_seeds):
            key = jax.random.fold_in(base_key, s)
            observations = jax.device_put(jnp.asarray(observations_all[s], dtype))
            states = jax.device_put(jnp.asarray(states_all[s], dtype))
            first, (rmse_a, resample_fraction) = time_call(twin, key, observations, states)
            times = [time_call(twin, key, observations, states)[0] for _ in range(args.repeats)]
            seconds = statistics.median(times)
            if s == 0:
                entry["compile_s"] = first - seconds
            entry["seconds"].append(seconds)
            entry["rmse_a"].append(float(rmse_a))
            if not np.isnan(float(resample_fraction)):
                entry.setdefault("resample_fraction", []).append(float(resample_fraction))
            entry["seeds"].append(s)
            print(f"cuthbert seed {s} {name}: {seconds:.4f} s, rmse.a {float(rmse_a):.4f}"
                  + (f", compile {entry['compile_s']:.2f} s" if s == 0 else ""),
                  file=sys.stderr, flush=True)
        entry["seconds_median"] = statistics.median(entry["seconds"])
        entry["rmse_a_mean"] = float(np.mean(entry["rmse_a"]))
        entry["analyses"] = int(num_obs)
        entry["analyses_averaged"] = int(num_obs - args.first_averaged)
        results[name] = entry

    results["_meta"] = {
        "cuthbert_version": cuthbert.__version__,
        "jax_version": jax.__version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "dtype": str(dtype),
        "data": os.path.abspath(args.data),
        "api": args.api,
        "args": vars(args),
        "notes": (
            "Model copied from ot_filter.models.lorenz63() defaults (x0 (1.509,-1.531,25.46), "
            "initial cov 2 I, obs var 2, 25 RK4 steps of 0.01, no process noise unless "
            "--process-noise). Particle filter: cuthbert.smc.particle_filter.build_filter with "
            "resampling_fn = ess_decorator(systematic + ot_filter-style regularisation jitter "
            f"{args.jitter} * N^(-1/7) * C_w^(1/2), threshold {args.ess_threshold}); mean = "
            "weighted mean before the (deferred) resampling. EnKF: cuthbert.ensemble_kalman."
            "ensemble_kalman_filter.build_filter (stochastic, perturbed obs; cuthbert has no "
            "square-root EnKF), inflation on forecast anomalies. Both also accumulate the "
            "log normalising constant (cuthbert always does). 'offline' api stores every state "
            "(particles [T+1, N, 3]); on CPU cuthbert's systematic resampling calls a numba "
            "inverse-CDF through jax.pure_callback (host round trip per resampling). Timed: one "
            "jitted filter run + rmse.a per call, block_until_ready, median of --repeats; "
            "compile_s = first call - median steady call (first seed)."
        ),
    }
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
