"""The chapter's Lorenz-63 experiment: components 1 and 3 observed, the OT filter against EnKF and SIR.

Setting (../shared/paper/NOTES.md): sigma 10, rho 28, beta 8/3, Euler steps of dt = 0.01, one
observation per step for 500 steps (t in (0, 5]), components 1 and 3 observed with noise variance
10. The truth starts from N(25 * 1, 100 I) and follows the deterministic dynamics (as in the
authors' script); the particles start from N(0, 100 I) and get process noise of std sqrt(0.1) per
step. Every method, the EnKF included, uses the model's own observation noise (variance 10).

Methods: ``enkf``, ``sir``, ``ot`` (OT filter without the EnKF layer) and ``ot_enkf`` (with it),
and optionally a large SIR (``reference_particles``, e.g. 10^5) as the exact-Bayes level.
Measured per simulation: MSE(t) of the ensemble mean, averaged over the 3 components; whether it
is below 1 at every t > 1.5 (``settled``) and on average over t > 1.5; compile and run seconds.

Note: "MSE below 1 at every t > 1.5" is out of reach of ANY filter here, exact Bayes included:
with process noise 0.1 per step and two of three components observed with variance 10 the
posterior variance is about 0.5-1 per component, so the squared error of the posterior mean
exceeds 1 at a fraction of the times (a 10^5-particle SIR does in every simulation, at the same
times as the other filters). The time average over t > 1.5 is the attainable criterion.

OT settings (measured on 3 + 10 simulations): width 32 and mini-batch 128 (the package's sizes
at n <= 2) with the 1024 -> 64 schedule match the exact-Bayes level; the authors' width 64 /
batch 64 is not better and 25% slower. With the EnKF layer, f needs the authors' Adam(1e-3):
with the slower default f of the time (1e-4) the learned correction extrapolates badly in the first steps (the prior N(0, 100 I) is
far from the truth near 25) and the MSE sits at 300-700 for ~50 steps.

Five T steps per outer iteration instead of the package's ten: on the runner's 10 truths
(``ot-filter run lorenz63``, one run each) the OT filter's MSE after t = 1.5 was 0.691 +- 0.043
with ten and 0.702 +- 0.049 with five, in 272 s and 130 s (10 simulations sharded over 2 cores);
with the EnKF layer and five, 0.604 +- 0.036.

f's rate 3e-4 (the package default since the size rule; 1e-4 before) and a floor of 32 outer
iterations per step instead of 64: on 10 truths (N = 1000, 500 steps, one core, one run) the MSE
after t = 1.5 was 0.738 +- 0.038 with 1e-4 and 64 (202 s of filtering), 0.698 +- 0.034 with 3e-4
and 64 (paired difference -0.040 +- 0.011, 223 s) and 0.723 +- 0.035 with 3e-4 and 32 (paired
-0.015 +- 0.011 against the first, 118 s). The floor of 32 with 1e-4 had cost +0.042 +- 0.014:
the faster f keeps up with half the iterations.
"""

from __future__ import annotations

from typing import Sequence

import jax
import numpy as np
import optax

from ot_filter.experiments._common import compile_and_run, diverged_flags, save_figure, simulate_truths, stats
from ot_filter.filtering import run_filter
from ot_filter.models import lorenz63
from ot_filter.updates import enkf, ot, sir

METHODS = ("enkf", "sir", "ot", "ot_enkf")
LABELS = {"enkf": "EnKF", "sir": "SIR", "ot": "OT", "ot_enkf": "OT + EnKF layer", "reference": "SIR, large (exact Bayes)"}
COLOURS = {"enkf": "tab:blue", "sir": "tab:orange", "ot": "tab:green", "ot_enkf": "tab:purple", "reference": "black"}
TIME_STEP = 0.01
SETTLE_TIME = 1.5
MSE_TARGET = 1.0
# The OT filter: warm start, 1024 outer iterations at the first step halving to 32, 5 T steps
# per f step (half the cost, the same MSE), width 32 and mini-batches of 128 (ot()'s size rule
# would give n = 3 width 64 and 256 pairs, twice the cost per iteration), otherwise the package
# defaults (f's rate 3e-4). See the module docstring for the measurements.
OT_OPTIONS = {"num_iterations": (1024, 32), "inner_steps": 5, "width": 32, "batch_size": 128, "concavity_points": 0}
# With the EnKF layer, f learns at the authors' rate and keeps the floor of 64 it was measured
# with (see the module docstring).
OT_ENKF_LAYER_OPTIONS = {"enkf_layer": True, "potential_optimizer": optax.adam(1e-3)}
OT_ENKF_LAYER_ITERATIONS = (1024, 64)
_SETTING = dict(dt=TIME_STEP, integrator="euler", steps_per_observation=1, observed=(0, 2),
                observation_noise_std=10.0**0.5, initial_std=10.0)


def lorenz63_models(observed: Sequence[int] = (0, 2)):
    """``(truth_model, filter_model)`` of the chapter's setting (see the module docstring). Models
    are pytrees of bound functions compared by value: rebuilding them reuses compiled programs.
    ``observed``: the observed components (the chapter's 1 and 3; e.g. ``(0,)``: x1 only)."""
    setting = dict(_SETTING, observed=tuple(observed))
    truth = lorenz63(process_noise_std=0.0, initial_mean=(25.0, 25.0, 25.0), **setting)
    filtering = lorenz63(process_noise_std=0.1**0.5, initial_mean=(0.0, 0.0, 0.0), **setting)
    return truth, filtering


def _updates(methods, ot_options):
    options = dict(OT_OPTIONS, **(ot_options or {}))
    layer_options = {**OT_OPTIONS, "num_iterations": OT_ENKF_LAYER_ITERATIONS, **(ot_options or {}),
                     **OT_ENKF_LAYER_OPTIONS}
    builders = {
        "enkf": lambda: enkf(),
        "sir": lambda: sir(),
        "ot": lambda: ot(**options),
        "ot_enkf": lambda: ot(**layer_options),
    }
    unknown = [name for name in methods if name not in builders]
    if unknown or not methods:
        raise ValueError(f"methods must be a non-empty subset of {list(builders)}, got {list(methods)}")
    return {name: builders[name]() for name in methods}


def run_lorenz63(
    key: jax.Array,
    num_particles: int = 1000,
    num_steps: int = 500,
    num_simulations: int = 10,
    methods: Sequence[str] = METHODS,
    ot_options: dict | None = None,
    save_every: int = 5,
    reference_particles: int = 0,
    progress: int = 0,
    observed: Sequence[int] = (0, 2),
    extra_updates: dict | None = None,
    filter_key: jax.Array | None = None,
) -> dict:
    """Runs every method on ``num_simulations`` independent truths (vmapped, one compiled program
    per method). Returns ``{"metrics": JSON-ready dict, "arrays": NumPy arrays}``; the arrays hold
    the first simulation's truth and the particles of every ``save_every``-th step for figures.
    ``reference_particles`` > 0 adds a SIR with that many particles (saved: its mean only);
    ``progress`` > 0 reports every that many steps to ``ot_filter.progress`` listeners;
    ``observed``: the observed components; ``extra_updates``: ``{name: update}`` run after the
    named methods on the same truths (e.g. an amortised OT filter, ``experiments/amortised.py``);
    ``filter_key``: the filters' key instead of the one derived from ``key`` (other filter
    randomness on the same truths)."""
    truth_model, filter_model = lorenz63_models(observed)
    updates = _updates(methods, ot_options) if methods or not extra_updates else {}
    clash = set(updates) & set(extra_updates or {})
    if clash:
        raise ValueError(f"extra_updates repeat methods already run: {sorted(clash)}")
    updates.update(extra_updates or {})
    if reference_particles:
        updates["reference"] = sir()
    truth_key, derived_key = jax.random.split(key)
    filter_key = derived_key if filter_key is None else filter_key
    states, observations = simulate_truths(truth_key, truth_model, num_steps, num_simulations)
    times = TIME_STEP * np.arange(1, num_steps + 1)
    settled_from = int(np.searchsorted(times, SETTLE_TIME, side="right"))
    summary = {"num_particles": num_particles, "num_steps": num_steps, "num_simulations": num_simulations,
               "observed": list(observed),
               "ot_options": {k: (list(v) if isinstance(v, tuple) else v)
                              for k, v in dict(OT_OPTIONS, **(ot_options or {})).items()},
               "ot_enkf_layer_options": {"potential_optimizer": "optax.adam(1e-3)"},
               "settle_time": SETTLE_TIME, "mse_target": MSE_TARGET}
    arrays = {"times": times, "states": np.asarray(states[0]), "observations": np.asarray(observations[0])}
    for index, (name, update) in enumerate(updates.items()):
        keys = jax.random.split(jax.random.fold_in(filter_key, index), num_simulations)

        is_reference = name == "reference"

        def one(k, y, update=update, is_reference=is_reference):
            result = run_filter(k, filter_model, update, y, reference_particles if is_reference else num_particles,
                                save_every=0 if is_reference else save_every, progress=progress)
            return result.mean, result.particles, diverged_flags(result.info)

        (mean, particles, diverged), timing = compile_and_run(jax.vmap(one), keys, observations)
        mse = np.mean((mean - np.asarray(states)) ** 2, axis=-1)  # [S, T]
        late = mse[:, settled_from:].max(axis=1)
        summary[name] = {
            "mse_over_time": np.exp(np.log(mse).mean(axis=0)).round(4).tolist(),  # geometric mean
            "mse_after_settle": stats(mse[:, settled_from:].mean(axis=1)),
            "mse_after_settle_per_simulation": mse[:, settled_from:].mean(axis=1).round(4).tolist(),  # for pairing
            "max_mse_after_settle_per_simulation": late.round(4).tolist(),
            "settled_simulations": int(np.sum(late < MSE_TARGET)),
            "settled_on_average_simulations": int(np.sum(mse[:, settled_from:].mean(axis=1) < MSE_TARGET)),
            "fraction_of_late_steps_below_target": float(np.mean(mse[:, settled_from:] < MSE_TARGET)),
            "compile_s": timing["compile_s"],
            "run_s": timing["run_s"],
            "seconds_per_step": timing["run_s"] / num_steps,
            "seconds_per_step_and_simulation": timing["run_s"] / (num_steps * num_simulations),
            "all_finite": bool(np.all(np.isfinite(mse))),
        }
        if diverged is not None:
            summary[name]["diverged_steps"] = int(np.sum(diverged))
        arrays[f"{name}_mse"] = mse
        arrays[f"{name}_mean"] = mean[0]
        if not is_reference:
            arrays[f"{name}_particles"] = particles[0]
    arrays["saved_times"] = times[save_every - 1::save_every]
    return {"metrics": summary, "arrays": arrays}


def plot_lorenz63(result: dict, out_dir: str) -> list[str]:
    """The unobserved second component with particles (first simulation), and MSE over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary, arrays = result["metrics"], result.get("arrays")  # no arrays: the MSE figure only
    methods = [m for m in METHODS if m in summary]
    times = TIME_STEP * np.arange(1, summary["num_steps"] + 1)
    paths = []
    if arrays is not None:
        paths.append(_plot_trajectories(plt, summary, arrays, methods, times, out_dir))

    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    for name in methods + (["reference"] if "reference" in summary else []):
        ax.plot(times, summary[name]["mse_over_time"], color=COLOURS[name],
                label=f"{LABELS[name]}: mean after {SETTLE_TIME:g} {summary[name]['mse_after_settle']['mean']:.2f}; "
                      f"{summary[name]['settled_on_average_simulations']}/{summary['num_simulations']} below 1 "
                      f"on average, {summary[name]['settled_simulations']} at every t")
    ax.axhline(MSE_TARGET, color="k", lw=0.6, ls=":")
    ax.axvline(SETTLE_TIME, color="k", lw=0.6, ls="--")
    ax.set(yscale="log", xlabel="time t", ylabel="MSE of the ensemble mean",
           title=f"Lorenz-63: MSE over time (geometric mean of {summary['num_simulations']} simulations)")
    ax.legend(fontsize=7)
    paths.append(save_figure(fig, out_dir, "lorenz63_mse.png"))
    return paths


def _plot_trajectories(plt, summary, arrays, methods, times, out_dir):
    fig, axes = plt.subplots(len(methods), 1, figsize=(8, 2.2 * len(methods)), sharex=True, squeeze=False)
    for ax, name in zip(axes[:, 0], methods):
        particles = arrays[f"{name}_particles"][..., 1]  # [S, N]
        shown = particles[:, :: max(1, particles.shape[1] // 100)]
        ax.scatter(np.repeat(arrays["saved_times"], shown.shape[1]), shown.ravel(), s=1, alpha=0.2,
                   color=COLOURS[name], label="particles")
        ax.plot(times, arrays["states"][:, 1], "k", lw=1.2, label="truth")
        ax.plot(times, arrays[f"{name}_mean"][:, 1], color="r", lw=0.8, ls="--", label="filter mean")
        ax.set(ylabel="$x_2$ (unobserved)", title=LABELS[name], ylim=(-40, 40))
        ax.legend(fontsize=7, loc="upper right", markerscale=5, ncol=3)
    axes[-1, 0].set_xlabel("time t")
    fig.suptitle(f"Lorenz-63, components 1 and 3 observed, N = {summary['num_particles']} (first simulation)")
    return save_figure(fig, out_dir, "lorenz63_trajectory.png")
