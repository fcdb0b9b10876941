"""The bimodal continuous-time example: FPF gains against the exact posterior.

Model (``continuous.squared_observation_sde``): a static state X ~ N(0, 1) observed through
dY = X^2 dt + dW. The truth is X = ``true_state``; the posterior
p(x | Y_t) ∝ exp(-x^2 / 2 + x^2 Y_t - x^4 t / 2) has two mirror-image modes at about +-|X|, and it
is also the exact posterior of the Euler-Maruyama-discretised model, so a grid gives it exactly.
The constant gain Cov(X, X^2) is zero for a symmetric ensemble: the constant-gain FPF barely moves
and stays near the prior. The kernel and learned gains approximate K = grad phi and should split
the ensemble into the two modes. As the issue's protocol also asks, a large SIR (10^5 particles)
on the discretised model is run and its own MMD to the exact posterior reported.

``run_bimodal_example`` returns JSON-ready metrics and NumPy arrays; ``plot_bimodal_example``
draws the figures. Both are what the benchmark script, the CLI and the notebook call.
"""

from __future__ import annotations

import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter import metrics
from ot_filter.continuous import (
    constant_gain,
    discretise,
    kernel_gain,
    learned_gain,
    run_fpf,
    simulate_sde,
    squared_observation_sde,
)
from ot_filter.experiments._common import stats
from ot_filter.filtering import run_filter
from ot_filter.updates import sir

GAINS = ("constant", "kernel", "learned")
GRID = np.linspace(-4.0, 4.0, 1601)
MMD_BANDWIDTH = 0.5  # about the width of one posterior mode at t ~ 1


def make_gain(name: str, options: dict | None = None):
    builders = {"constant": constant_gain, "kernel": kernel_gain, "learned": learned_gain}
    if name not in builders:
        raise ValueError(f"gain must be one of {list(builders)}, got {name!r}")
    return builders[name](**(options or {}))


def exact_posterior_masses(increments: np.ndarray, dt: float, steps: np.ndarray) -> np.ndarray:
    """``[S, G]`` masses on ``GRID`` of p(x | dY_0..dY_k) for each k in ``steps`` (sigma = 1)."""
    observed = np.cumsum(increments[:, 0])[steps]  # Y_{t_{k+1}}
    times = (steps + 1) * dt
    x2 = GRID**2
    log_density = -0.5 * x2[None] + observed[:, None] * x2[None] - 0.5 * times[:, None] * x2[None] ** 2
    density = np.exp(log_density - log_density.max(axis=1, keepdims=True))
    return density / density.sum(axis=1, keepdims=True)


def filter_bimodal_paths(
    key: jax.Array,
    gain_name: str,
    num_particles: int = 1000,
    dt: float = 0.01,
    num_steps: int = 200,
    true_state: float = 1.0,
    num_simulations: int = 4,
    save_every: int = 10,
    gain_options: dict | None = None,
    progress: int = 0,
) -> dict:
    """One gain on ``num_simulations`` paths drawn from ``key`` (the same paths for every gain).

    Returns NumPy arrays and numbers: ``times`` [S] of the saved steps, ``mmd`` and ``positive``
    (mass on x > 0) [R, S] per simulation, the first simulation's ``final_particles`` [N] and
    ``exact_final`` density on ``grid``, ``fallback_steps`` and ``rejected_updates`` (totals) and
    ``timing`` (compile and run seconds, measured separately).
    """
    from ot_filter.experiments._common import compile_and_run

    truth_model = squared_observation_sde(initial_mean=true_state, initial_std=1e-12)
    model = squared_observation_sde()
    keys = jax.random.split(key, num_simulations)
    paths = jax.vmap(lambda k: simulate_sde(jax.random.fold_in(k, 0), truth_model, dt, num_steps))(keys)
    increments = np.asarray(paths.increments)
    save_every = min(save_every, num_steps)
    steps = np.arange(save_every - 1, num_steps, save_every)
    exact = np.stack([exact_posterior_masses(inc, dt, steps) for inc in increments])  # [R, S, G]
    gain = make_gain(gain_name, gain_options)

    def filter_one(key, inc):
        out = run_fpf(jax.random.fold_in(key, 1), model, gain, inc, dt, num_particles,
                      save_every=save_every, progress=progress)
        return out.particles, getattr(out.info, "fallback", jnp.zeros(1, bool)), out.rejected_updates

    (particles, fallback, rejected), timing = compile_and_run(
        jax.vmap(filter_one), keys, jnp.asarray(increments), shard=False
    )  # particles [R, S, N, 1]
    grid = jnp.asarray(GRID, jnp.float32)
    distance = jax.jit(jax.vmap(jax.vmap(
        lambda x, w: metrics.mmd_to_product(x, grid, w[None], MMD_BANDWIDTH))))
    mmd = np.asarray(distance(jnp.asarray(particles), jnp.asarray(exact, jnp.float32)))
    return {
        "times": (steps + 1) * dt,
        "mmd": mmd,
        "positive": (particles[..., 0] > 0).mean(axis=-1),
        "final_particles": particles[0, -1, :, 0],
        "grid": GRID,
        "exact_final": exact[0, -1] / (GRID[1] - GRID[0]),
        "exact": exact,
        "increments": increments,
        "fallback_steps": int(np.sum(fallback)),
        "rejected_updates": int(np.sum(rejected)),
        "timing": timing,
    }


def run_bimodal_example(
    seed: int = 0,
    num_particles: int = 1000,
    dt: float = 0.01,
    num_steps: int = 200,
    true_state: float = 1.0,
    num_simulations: int = 4,
    gains: Sequence[str] = GAINS,
    save_every: int = 10,
    reference_particles: int = 100_000,
    gain_options: dict | None = None,
) -> tuple[dict, dict]:
    """Runs every gain on ``num_simulations`` paths; MMD to the exact posterior over time.

    Returns ``(metrics, arrays)``: per gain the MMD (h = 0.5) at the saved times (mean over
    simulations), its time average over the second half, the mass on the positive side (exact:
    1/2) and the seconds (compile and run); arrays hold the times, the exact densities and the
    final ensembles of the first simulation for the figures. ``reference_particles`` > 0 adds the
    large-SIR check (0: skip it).
    """
    gain_options = gain_options or {}
    results: dict = {"gains": {}}
    finals = {}
    for name in gains:
        out = filter_bimodal_paths(
            jax.random.key(seed), name, num_particles, dt, num_steps, true_state, num_simulations,
            save_every, gain_options.get(name),
        )
        times, mmds, positive = out["times"], out["mmd"], out["positive"]
        late = times >= times[-1] / 2
        seconds = out["timing"]["run_s"]
        results["gains"][name] = {
            "mmd_over_time": mmds.mean(axis=0).tolist(),
            "mmd_late": stats(mmds[:, late].mean(axis=1)),
            "positive_mass_final": stats(positive[:, -1]),
            "seconds": seconds,
            "compile_seconds": out["timing"]["compile_s"],
            "seconds_per_step_and_simulation": seconds / (num_steps * num_simulations),
            "fallback_steps": out["fallback_steps"],
            "rejected_updates": out["rejected_updates"],
        }
        finals[name] = out["final_particles"]
    exact, increments = out["exact"], out["increments"]
    keys = jax.random.split(jax.random.key(seed), num_simulations)
    model = squared_observation_sde()
    grid = jnp.asarray(GRID, jnp.float32)
    results["setting"] = {
        "seed": seed, "num_particles": num_particles, "dt": dt, "num_steps": num_steps,
        "true_state": true_state, "num_simulations": num_simulations, "save_every": save_every,
        "mmd_bandwidth": MMD_BANDWIDTH, "gain_options": {k: repr(v) for k, v in gain_options.items()},
    }
    arrays = {"times": times, "grid": GRID, "exact_final": out["exact_final"],
              **{f"final_{name}": value for name, value in finals.items()}}
    if not reference_particles:
        return results, arrays

    # The protocol: a large SIR on the discretised model, checked against the exact posterior.
    discretised = discretise(model, dt)

    def sir_one(key, inc):
        return run_filter(jax.random.fold_in(key, 2), discretised, sir(), inc, reference_particles,
                          save_every=num_steps, update_first=True)

    start = time.perf_counter()
    reference_runs = [sir_one(k, jnp.asarray(inc)) for k, inc in zip(keys, increments)]
    reference_mmd = [
        float(metrics.mmd_to_product(r.particles[-1], grid, jnp.asarray(e[-1:], jnp.float32), MMD_BANDWIDTH,
                                     weights=jnp.exp(r.log_weights[-1])))
        for r, e in zip(reference_runs, exact)
    ]
    results["sir_reference"] = {
        "particles": reference_particles,
        "mmd_to_exact_final": stats(reference_mmd),
        "seconds": time.perf_counter() - start,
    }
    return results, arrays


def plot_bimodal_example(results: dict, arrays: dict, out_dir: str) -> list[str]:
    """Two PNGs: MMD to the exact posterior over time, and the final ensembles vs the exact density."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ot_filter.experiments._common import save_figure

    names = list(results["gains"])
    fig, ax = plt.subplots(figsize=(6, 4))
    for name in names:
        ax.plot(arrays["times"], results["gains"][name]["mmd_over_time"], label=f"FPF, {name} gain")
    ax.set_xlabel("time t")
    ax.set_ylabel("MMD to the exact posterior (h = 0.5)")
    ax.set_title(f"Bimodal example dY = X² dt + dW, X = {results['setting']['true_state']}")
    ax.legend()
    ax.grid(alpha=0.3)
    paths = [save_figure(fig, out_dir, "bimodal_mmd_over_time.png")]

    fig, axes = plt.subplots(1, len(names), figsize=(4 * len(names), 3.4), sharey=True)
    for ax, name in zip(np.atleast_1d(axes), names):
        ax.hist(arrays[f"final_{name}"], bins=80, range=(-3, 3), density=True, alpha=0.6, label="particles")
        ax.plot(arrays["grid"], arrays["exact_final"], "k", lw=1.5, label="exact posterior")
        ax.set_xlim(-3, 3)
        ax.set_xlabel("state x")
        ax.set_title(f"{name} gain, t = {arrays['times'][-1]:.2f}")
    np.atleast_1d(axes)[0].set_ylabel("density")
    np.atleast_1d(axes)[0].legend()
    paths.append(save_figure(fig, out_dir, "bimodal_final_ensembles.png"))
    return paths
