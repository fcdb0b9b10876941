"""The experiments ``ot-filter run`` knows: their options, their cells and their figures.

An experiment is split into cells (method x swept option values x block of simulations), each an
independent, deterministic computation: its PRNG key derives from the seed and the cell's
coordinates, never from the order in which cells run, so a resumed sweep reproduces an
uninterrupted one. Truths depend on the block (and the dimension) but not on the method or the
particle count, so every method and every N sees the same simulations.

``run_cell(options, cell, progress)`` returns a ``CellOutput``: per-simulation numbers (JSON),
per-simulation curves over time, and arrays for figures; ``plot(options, groups, out)`` draws
the figures from the summarised groups (one per method and swept value).
"""

from __future__ import annotations

import functools
import math
import os
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["CellOutput", "Experiment", "EXPERIMENTS"]


class CellOutput(NamedTuple):
    per_simulation: dict  # name -> [S_block] floats (the summary's mean / s.e. come from these)
    counts: dict  # name -> int, summed over blocks (e.g. diverged OT trainings)
    curves: dict  # name -> [S_block, T] array (the summary averages them over simulations)
    arrays: dict  # name -> array, for figures (the summary keeps block 0's)
    timing: dict  # {"compile_s", "run_s"}


class Experiment(NamedTuple):
    name: str
    description: str
    defaults: dict  # option -> default value; only these options apply
    quick: dict  # overrides under --quick (each experiment then takes < 2 min on 2 cores)
    sweep: tuple  # options that may take several values (each value is its own cell)
    methods: tuple  # the methods it knows
    run_cell: Callable[[dict, dict, int], CellOutput]
    plot: Callable[[dict, list, str], list]
    minimum_steps: int = 1  # e.g. Lorenz-63 averages after t = 1.5 (150 steps)


def cell_key(seed: int, *coordinates: int) -> jax.Array:
    key = jax.random.key(seed)
    for value in coordinates:
        key = jax.random.fold_in(key, int(value))
    return key


def _timed(function, *args, **static):
    """(output as NumPy, {"compile_s", "run_s"}) for a ``jax.jit``-ted ``function`` of traced
    ``args`` and static keyword arguments ``static``. Compiled
    programs are JAX's own cache: models and updates are pytrees whose numbers are traced, so the
    cells of a sweep that differ only in numbers (or rebuilt objects) reuse one program."""
    start = time.perf_counter()
    compiled = function.lower(*args, **static).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    output = jax.block_until_ready(compiled(*args))
    run_s = time.perf_counter() - start
    return jax.tree.map(np.asarray, output), {"compile_s": compile_s, "run_s": run_s}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, out, name):
    from ot_filter.experiments._common import save_figure

    return save_figure(fig, out, name)


def _band(ax, x, curve, label, log=False, **style):
    """The mean curve with a +-2 s.e. band (on a log axis the band stops at a fifth of the mean)."""
    mean, se = np.asarray(curve["mean"]), np.asarray(curve["se"])
    line, = ax.plot(x, mean, label=label, **style)
    lower = np.maximum(mean - 2 * se, mean / 5) if log else mean - 2 * se
    ax.fill_between(x, lower, mean + 2 * se, color=line.get_color(), alpha=0.2, lw=0)


def _errorbar_vs(ax, groups, axis, metric, method_label, log=False):
    for method in dict.fromkeys(g["method"] for g in groups):
        rows = sorted((g for g in groups if g["method"] == method), key=lambda g: g[axis])
        x = [g[axis] for g in rows]
        mean = np.array([g["per_simulation"][metric]["mean"] for g in rows])
        se = np.array([2 * g["per_simulation"][metric]["se"] for g in rows])
        lower = np.minimum(se, 0.8 * mean) if log else se  # a log axis cannot show mean - 2 s.e. <= 0
        ax.errorbar(x, mean, yerr=(lower, se), marker="o", capsize=3, label=method_label(method))


def _particle_panels(plt, groups, times_key, component, ylabel, alpha, mirror=False, ylim=None):
    """One panel per method: the first simulation's particles (coordinate ``component``) at the
    saved times, the truth, and optionally its mirror image (the other mode of x -> x^2)."""
    fig, axes = plt.subplots(len(groups), 1, figsize=(7, 2.4 * len(groups)), sharex=True, squeeze=False)
    for ax, g in zip(axes[:, 0], groups):
        a = g["arrays"]
        times = np.repeat(a[times_key][:, None], a["particles"].shape[1], axis=1)
        ax.scatter(times, a["particles"][:, :, component], s=1, alpha=alpha, color="tab:blue")
        ax.plot(a["times"], a["states"][:, component], "k-", lw=1.5, label="truth")
        if mirror:
            ax.plot(a["times"], -a["states"][:, component], "k:", lw=1, label="mirror mode")
        ax.set(ylabel=ylabel, title=f"{_label(g['method'])} particles (first simulation)", ylim=ylim)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time t")
    return fig


LABELS = {"enkf": "EnKF", "sir": "SIR", "ot": "OT", "flow_matching": "flow matching", "ot_enkf": "OT + EnKF layer", "letkf": "LETKF",
          "letkf_etpf": "LETKF + LETPF (l^0.25)", "local_ot_etpf": "OT, localised + LETPF (l^0.25)",
          "local_ot": "OT, localised", "local_flow": "flow matching, localised", "amortised": "amortised OT (a)", "amortised_warm": "amortised OT (b)",
          "amortised_distilled": "amortised OT (a), distilled map",
          "local_amortised": "OT, localised, offline map (a)", "local_amortised_warm": "OT, localised, offline map (b)",
          "constant": "FPF, constant gain", "kernel": "FPF, kernel gain", "learned": "FPF, learned gain"}


def _label(method):
    return LABELS.get(method, method)


# --- the static example ------------------------------------------------------------------------


def _static_cell(options, cell, progress):
    from ot_filter.experiments.static_example import run_static_example

    del progress  # one Bayes update: nothing to report
    noise_index = options["noise"].index(cell["noise"])
    key = cell_key(options["seed"], noise_index, cell["block"])
    result = run_static_example(key, noise=cell["noise"], num_particles=cell["particles"],
                                num_seeds=cell["simulations"], dim=options["dim"][0],
                                methods=(cell["method"],))
    summary, arrays = result["metrics"][cell["method"]], result["arrays"]
    timing = {k: result["metrics"][k] for k in ("compile_s", "run_s")}
    positive = np.asarray(summary["positive_mass_per_seed"])
    per_sim = {"w1": summary["w1_per_seed"], "positive_mass_x1": positive[:, 0].tolist()}
    counts = {"simulations_holding_both_modes": summary["seeds_holding_both_modes"]}
    if "diverged_seeds" in summary:
        counts["diverged_trainings"] = summary["diverged_seeds"]
    figure_arrays = {"posterior": arrays[f"{cell['method']}_posterior"][0], "grid": arrays["grid"],
                     "density": arrays["density"]}
    return CellOutput(per_sim, counts, {}, figure_arrays, timing)


def _static_plot(options, groups, out):
    plt = _plt()
    paths = []
    for noise in options["noise"]:
        for particles in options["particles"]:
            rows = [g for g in groups if g["noise"] == noise and g["particles"] == particles]
            fig, axes = plt.subplots(1, len(rows), figsize=(4.2 * len(rows), 3.6), squeeze=False, sharey=True)
            for ax, g in zip(axes[0], rows):
                a = g["arrays"]
                ax.hist(a["posterior"][:, 0], bins=60, range=(-3, 3), density=True, alpha=0.6,
                        label="particles")
                ax.plot(a["grid"], a["density"], "k", lw=1.2, label="exact posterior")
                w1 = g["per_simulation"]["w1"]
                ax.set(xlim=(-3, 3), xlabel="$x_1$",
                       title=f"{_label(g['method'])}: W1 {w1['mean']:.3f} ± {w1['se']:.3f}")
                ax.legend(fontsize=8)
            axes[0, 0].set_ylabel("density")
            fig.suptitle(f"Static example: posterior of $x_1$ given y = 1 (noise {noise}, N = {particles})")
            paths.append(_save(fig, out, f"posterior_noise{noise}_N{particles}.png"))
    return paths


# --- the dynamic example -----------------------------------------------------------------------

DYNAMIC_KERNELS = {  # (bandwidth, standardise): the chapter's settings for each figure
    "dynamic": (1.0, False),
    "dynamic-dims": (4.0, True),
    "dynamic-particles": (0.6, True),
}


AMORTISED_METHODS = ("amortised", "amortised_warm", "amortised_distilled")
LOCAL_AMORTISED_METHODS = ("local_amortised", "local_amortised_warm")  # the dynamic example's


def _amortised(options, experiment, method, num_particles, **model):
    """``(methods, extra_updates)`` for a cell of ``method``: an amortised OT filter gets the map
    stored in the run directory (trained there by the first cell that needs it, reused by later
    cells, resumed runs and later runs into the same directory); so does the localised filter
    with an offline map (``experiments/local_amortised.py``)."""
    if method not in AMORTISED_METHODS + LOCAL_AMORTISED_METHODS:
        return (method,), None
    maps = options["maps"] or os.path.join(options["run_dir"], "maps")
    if method in LOCAL_AMORTISED_METHODS:
        from ot_filter.experiments.local_amortised import local_amortised_updates, local_map_for, local_map_name

        local_map, _ = local_map_for(os.path.join(maps, local_map_name(model["dim"])), cell_key(options["seed"], 999_979),
                                     model["dim"], num_particles=num_particles, num_steps=options["steps"],
                                     num_iterations=options["map_iterations"])
        return (), {method: local_amortised_updates(local_map, model["dim"])[method]}
    from ot_filter.experiments.amortised import (amortised_updates, distilled_map_for, map_for, map_name,
                                                 same_setting_candidates, warm_map_for)
    from ot_filter.updates.amortised import amortised_ot

    directory = os.path.join(maps, map_name(experiment, **model))
    # Offline trajectories as long as the run's, with its particle count.
    gate = options.get("map_gate")
    trained, _ = map_for(directory, cell_key(options["seed"], 999_983), experiment, num_particles=num_particles,
                         num_steps=options["steps"], num_iterations=options["map_iterations"],
                         gate=False if gate == 0 else gate, **model)
    if method == "amortised_distilled":
        # The offline stage's trainings of the kept map's setting, their average fitted into one map
        # (narrower where the state is small: distilled_width), stored beside the kept map.
        student = distilled_map_for(os.path.join(directory, "distilled"), cell_key(options["seed"], 999_961), trained,
                                    experiment, num_particles=num_particles, num_steps=options["steps"],
                                    num_iterations=options["map_iterations"],
                                    teachers=same_setting_candidates(directory, trained), **model)
        return (), {method: amortised_ot(student)}
    # (b) from the candidate the stage kept for it (Lorenz-63), else from the map kept for (a)
    return (), {method: amortised_updates(trained, experiment, warm_map_for(directory, trained))[method]}


def _dynamic_cell(options, cell, progress):
    from ot_filter.experiments.dynamic_example import run_dynamic_example

    bandwidth, standardise = DYNAMIC_KERNELS[options["experiment"]]
    key = cell_key(options["seed"], cell["dim"], cell["block"])
    methods, extra = _amortised(options, "dynamic", cell["method"], cell["particles"], dim=cell["dim"])
    result = run_dynamic_example(
        key, dim=cell["dim"], num_particles=cell["particles"], num_steps=options["steps"], progress=progress,
        num_simulations=cell["simulations"], methods=methods, bandwidth=bandwidth,
        standardise=standardise, average_from=min(1.0, 0.1 * options["steps"]), keep=1, extra_updates=extra,
    )
    method = cell["method"]
    summary, arrays = result["metrics"][method], result["arrays"]
    timing = {"compile_s": summary["compile_s"], "run_s": summary["run_s"]}
    counts = {k: summary[k] for k in ("diverged_steps",) if k in summary}
    figure_arrays = {"times": arrays["times"], "states": arrays["states"][0],
                     "particles": arrays[f"{method}_particles"][0]}
    exact = summary["exact"]
    return CellOutput({"mmd_average": summary["mmd_average_per_simulation"],
                       "w1": exact["w1_per_simulation"],
                       "floor_w1": result["metrics"]["floor"]["w1_per_simulation"]},
                      counts,
                      {"mmd": arrays[f"{method}_mmd"], "w1": arrays[f"{method}_w1"]}, figure_arrays, timing)


def _dynamic_plot(options, groups, out):
    plt = _plt()
    experiment = options["experiment"]
    paths = []
    if experiment == "dynamic":
        for curve, ylabel, name in (("mmd", "MMD to the exact posterior (the chapter's metric)", "mmd_over_time.png"),
                                    ("w1", "W1 to the exact marginals (mean over coordinates)", "w1_over_time.png")):
            fig, ax = plt.subplots(figsize=(6.5, 4))
            for g in groups:
                _band(ax, g["arrays"]["times"], g["curves"][curve], _label(g["method"]))
            if curve == "w1":
                ax.axhline(groups[0]["per_simulation"]["floor_w1"]["mean"], color="k", ls="--", lw=1,
                           label="N exact samples (floor)")
            ax.set(xlabel="time t", ylabel=ylabel,
                   title=f"Dynamic example, n = {options['dim'][0]}, N = {options['particles'][0]} "
                         f"({options['simulations']} simulations, band: ±2 s.e.)")
            ax.legend()
            ax.grid(alpha=0.3)
            paths.append(_save(fig, out, name))
        fig = _particle_panels(plt, groups, "times", 0, "$x_1$", alpha=0.1, mirror=True)
        paths.append(_save(fig, out, "particles_over_time.png"))
    else:
        axis = "dim" if experiment == "dynamic-dims" else "particles"
        for metric, ylabel in (("mmd_average", "time-averaged MMD (standardised, the chapter's)"),
                               ("w1", "time-averaged W1 to the exact marginals")):
            fig, ax = plt.subplots(figsize=(6, 4))
            _errorbar_vs(ax, groups, axis, metric, _label, log=axis == "particles")
            if metric == "w1":
                floors = sorted({(g[axis], g["per_simulation"]["floor_w1"]["mean"]) for g in groups})
                ax.plot([x for x, _ in floors], [f for _, f in floors], "k--", lw=1, label="N exact samples (floor)")
            if axis == "particles":
                ax.set_xscale("log")
                ax.set_yscale("log")
            ax.set(xlabel="state dimension n" if axis == "dim" else "number of particles N", ylabel=ylabel,
                   title=f"Dynamic example: {'MMD' if metric == 'mmd_average' else 'W1'} vs "
                         f"{'dimension' if axis == 'dim' else 'particle count'} (±2 s.e.)")
            ax.legend()
            ax.grid(alpha=0.3, which="both")
            paths.append(_save(fig, out, f"{'mmd' if metric == 'mmd_average' else 'w1'}_vs_"
                                         f"{'dimension' if axis == 'dim' else 'particles'}.png"))
    paths.extend(_offline_curves(options, groups, out))
    return paths


def _offline_curves(options, groups, out):
    """The offline training curves (J on held-out ensembles) of the maps the run's amortised
    methods used, in one figure (none when no such method ran)."""
    from ot_filter.experiments.amortised import map_name, plot_validation
    from ot_filter.experiments.local_amortised import local_map_name

    maps = options.get("maps") or os.path.join(out, "maps")
    curves = {}
    for g in groups:
        if g["method"] in AMORTISED_METHODS + LOCAL_AMORTISED_METHODS:
            local = g["method"] in LOCAL_AMORTISED_METHODS
            name = local_map_name(g["dim"]) if local else map_name("dynamic", dim=g["dim"])
            history = os.path.join(maps, name, "history.npz")
            if os.path.exists(history):
                with np.load(history) as arrays:
                    curves[f"{'local map' if local else 'map'}, n = {g['dim']}"] = dict(arrays)
    title = "Offline training: J on held-out ensembles\nand on the training batches (rounds: dotted)"
    return [plot_validation(curves, out, "offline_training.png", title)] if curves else []


# --- Lorenz-63 (the chapter's setting) and Lorenz-96 (DAPPER's twin experiment) ---------------------


def _lorenz63_cell(options, cell, progress):
    from ot_filter.experiments.lorenz63 import SETTLE_TIME, run_lorenz63

    key = cell_key(options["seed"], cell["block"])
    methods, extra = _amortised(options, "lorenz63", cell["method"], cell["particles"], observed=(0, 2))
    result = run_lorenz63(key, num_particles=cell["particles"], num_steps=options["steps"],
                          num_simulations=cell["simulations"], methods=methods, save_every=5,
                          progress=progress, extra_updates=extra)
    method = cell["method"]
    summary, arrays = result["metrics"][method], result["arrays"]
    mse = arrays[f"{method}_mse"]  # [S, T]
    settled = arrays["times"] > SETTLE_TIME
    counts = {k: summary[k] for k in ("diverged_steps",) if k in summary}
    figure_arrays = {"times": arrays["times"], "states": arrays["states"], "saved_times": arrays["saved_times"],
                     "particles": arrays[f"{method}_particles"]}
    return CellOutput({"mse_after_settle": mse[:, settled].mean(axis=1).tolist()}, counts,
                      {"mse": mse}, figure_arrays,
                      {"compile_s": summary["compile_s"], "run_s": summary["run_s"]})


def _lorenz63_plot(options, groups, out):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for g in groups:
        _band(ax, g["arrays"]["times"], g["curves"]["mse"], _label(g["method"]), log=True)
    ax.set(yscale="log", xlabel="time t", ylabel="MSE of the ensemble mean",
           title=f"Lorenz-63 (x1, x3 observed), N = {options['particles'][0]}, "
                 f"{options['simulations']} simulations")
    ax.axhline(1.0, color="grey", ls=":", lw=1)
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    paths = [_save(fig, out, "lorenz63_mse.png")]
    fig = _particle_panels(plt, groups, "saved_times", 1, "$x_2$ (unobserved)", alpha=0.05, ylim=(-40, 40))
    paths.append(_save(fig, out, "lorenz63_particles.png"))
    return paths


# Lorenz-96's localised updates: radius 4 for the LETKF (DAPPER's sakov2008 tuning, Gaspari-Cohn),
# and for the localised OT filter the same taper in its deterministic layer (windows out to the
# taper's support, 29 observations: the layer IS that LETKF), inflation 1.04, and fresh networks
# at every step trained for 64 iterations, so that T starts from the layer. RMSE 0.239 against
# the LETKF's 0.231; windows of 4 observations either side with a step taper gave 0.258.
# Warm-started from step to step the shared map drifted (its J crept from 0 to 0.1-0.2 after 200
# steps and the RMSE doubled); a loss bound that restarted it still left RMSE 0.301
# (``benchmarks/ot_lorenz96.py`` measures them). Mini-batches of 128 local pairs: every Lorenz-96
# figure was measured with them. local_ot's default of 512 (0.2.19), 16 truths, one run per
# operator: squared observations 0.773 against 0.821 (the LETKF 0.766; 512 - 128 = -0.048 +- 0.041,
# not resolved), linear 0.2319 against 0.2331 (-0.0013 +- 0.0004), at 3.4-3.5 times the seconds
# (``benchmarks/results/ot_lorenz96/batch_fresh_16/``): not enough to pay for the CLI's default run.
LORENZ96_LOCAL = dict(letkf_radius=4.0, ot_taper_radius=4.0, ot_state_radius=0.0, inflation=1.04, ot_iterations=64,
                      ot_batch_size=128)


def lorenz96_local_ot(model, num_iterations, taper: str = "gaspari_cohn", inflation: float | None = None,
                      **options):
    """The catalogue's localised OT update on ``model``'s geometry: the deterministic layer with
    ``taper`` at ``LORENZ96_LOCAL``'s radius (Gaspari-Cohn: windows out to its support) and its
    inflation unless ``inflation`` is given."""
    import ot_filter as otf
    from ot_filter.localisation import taper_support

    local = LORENZ96_LOCAL
    radius = local["ot_taper_radius"]
    windows = otf.local_windows(model.geometry, taper_support(radius, taper), local["ot_state_radius"])
    options = {"batch_size": local["ot_batch_size"], **options}
    return otf.local_ot(windows, num_iterations=num_iterations, enkf_layer="deterministic", taper=taper,
                        inflation=local["inflation"] if inflation is None else inflation, **options)


def lorenz96_update(method: str, model=None):
    """Lorenz-96 updates: DAPPER's square-root EnKF with inflation 1.02 (DAPPER tunes 1.013 for
    N = 24), the LETKF, the regularised SIR of the Lorenz-63 benchmark, the OT filter with the
    1024 -> 64 schedule (the chapter's sizes), the localised OT filter (``LORENZ96_LOCAL``) and
    the hybrids that finish with the LETPF on a quarter of the likelihood (``experiments._common.then_etpf``)
    after the LETKF (``letkf_etpf``) or after the localised OT filter (``local_ot_etpf``). The
    localised updates need the ``model``'s geometry."""
    import ot_filter as otf
    from ot_filter.experiments.twin_configurations import TWIN_CONFIGURATIONS

    if method == "enkf":
        return TWIN_CONFIGURATIONS["L96/EnKF-Sqrt-N24"].build_update(inflation=1.02)
    if method == "sir":
        return TWIN_CONFIGURATIONS["L63/PartFilt-N800"].build_update()
    if method == "ot":
        # The n = 2 sizes and f rate, not ot()'s rule for n = 40 (width 256, batches of 1024):
        # that is over 10 times the work per iteration, hours for the 4 x 500 steps on 2 CPU cores,
        # for a filter that falls back to the EnKF every 20-50 steps; the localised OT filter is
        # the one for this model (measured figures: docs/ot_at_scale.md, Lorenz-96).
        return otf.ot(num_iterations=(1024, 64), width=32, batch_size=128, potential_learning_rate=1e-4)
    if model is None:
        raise ValueError(f"the {method!r} update needs the model (its geometry)")
    local = LORENZ96_LOCAL
    if method == "letkf":
        return otf.letkf(otf.localisation(model.geometry, local["letkf_radius"]), inflation=local["inflation"])
    if method == "local_ot":
        return lorenz96_local_ot(model, local["ot_iterations"], warm_start=False)
    if method == "letkf_etpf":
        from ot_filter.experiments._common import letkf_etpf

        return letkf_etpf(otf.localisation(model.geometry, local["letkf_radius"]), inflation=local["inflation"])
    if method == "local_ot_etpf":
        from ot_filter.experiments._common import then_etpf

        return then_etpf(lorenz96_local_ot(model, local["ot_iterations"], warm_start=False),
                         otf.localisation(model.geometry, local["letkf_radius"]))
    raise ValueError(f"unknown Lorenz-96 method {method!r}")


@functools.partial(jax.jit, static_argnames=("num_particles", "progress"))
def _lorenz96_means(keys, model, update, observations, num_particles, progress):
    """Filter means ``[S, T, n]`` of every simulation (one program per shapes and structure)."""
    import ot_filter as otf

    def one(key, y):
        return otf.run_filter(key, model, update, y, num_particles, save_every=0, progress=progress).mean

    return jax.vmap(one)(keys, observations)


def _lorenz96_cell(options, cell, progress):
    from ot_filter import metrics
    from ot_filter.experiments._common import simulate_truths
    from ot_filter.experiments.twin_configurations import twin_model

    model = twin_model("lorenz96", dim=cell["dim"])
    truth_key, filter_key = jax.random.split(cell_key(options["seed"], cell["dim"], cell["block"]))
    states, observations = (np.asarray(a) for a in simulate_truths(
        truth_key, model, options["steps"], cell["simulations"]))
    means, timing = _timed(
        _lorenz96_means, jax.random.split(filter_key, cell["simulations"]), model,
        lorenz96_update(cell["method"], model), observations,
        num_particles=cell["particles"], progress=progress,
    )
    rmse = np.asarray(jax.vmap(metrics.rmse)(jnp.asarray(means), jnp.asarray(states)))  # [S, T]
    late = slice(options["steps"] // 2, None)  # DAPPER averages after a burn-in; here the 2nd half
    times = 0.05 * np.arange(1, options["steps"] + 1)
    return CellOutput({"rmse_a": rmse[:, late].mean(axis=1).tolist()}, {}, {"rmse": rmse},
                      {"times": times}, timing)


def _lorenz96_plot(options, groups, out):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for g in groups:
        mean = g["per_simulation"]["rmse_a"]["mean"]
        _band(ax, g["arrays"]["times"], g["curves"]["rmse"],
              f"{_label(g['method'])} (n = {g['dim']}): rmse.a {mean:.2f}", log=True)
    ax.set(yscale="log", xlabel="time (model units)", ylabel="analysis RMSE",
           title=f"Lorenz-96 twin experiment, N = {options['particles'][0]} "
                 f"({options['simulations']} simulations; noise std 1)")
    ax.axvline(0.05 * (options["steps"] // 2), color="grey", ls=":", lw=1)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    return [_save(fig, out, "lorenz96_rmse.png")]


# --- continuous time: the FPF on dY = X^2 dt + dW -------------------------------------------------


def _continuous_cell(options, cell, progress):
    from ot_filter.experiments.continuous_time import filter_bimodal_paths

    out = filter_bimodal_paths(cell_key(options["seed"], cell["block"]), cell["method"],
                               num_particles=cell["particles"], dt=options["dt"],
                               num_steps=options["steps"], num_simulations=cell["simulations"],
                               progress=progress)
    late = out["times"] >= out["times"][-1] / 2
    per_sim = {"mmd_average": out["mmd"][:, late].mean(axis=1).tolist(),
               "positive_mass_final": out["positive"][:, -1].tolist()}
    counts = {"fallback_steps": out["fallback_steps"], "rejected_updates": out["rejected_updates"]}
    figure_arrays = {k: out[k] for k in ("times", "grid", "exact_final", "final_particles")}
    return CellOutput(per_sim, counts, {"mmd": out["mmd"]}, figure_arrays, out["timing"])


def _continuous_plot(options, groups, out):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for g in groups:
        _band(ax, g["arrays"]["times"], g["curves"]["mmd"], _label(g["method"]))
    ax.set(xlabel="time t", ylabel="MMD to the exact posterior (h = 0.5)",
           title=f"FPF on dY = X² dt + dW (X = 1), N = {options['particles'][0]}, dt = {options['dt']}")
    ax.legend()
    ax.grid(alpha=0.3)
    paths = [_save(fig, out, "fpf_mmd_over_time.png")]
    fig, axes = plt.subplots(1, len(groups), figsize=(4 * len(groups), 3.4), sharey=True, squeeze=False)
    for ax, g in zip(axes[0], groups):
        a = g["arrays"]
        bins = int(np.clip(len(a["final_particles"]) // 12, 20, 80))  # ~12 particles a bin or more
        ax.hist(a["final_particles"], bins=bins, range=(-3, 3), density=True, alpha=0.6, label="particles")
        ax.plot(a["grid"], a["exact_final"], "k", lw=1.5, label="exact posterior")
        ax.set(xlim=(-3, 3), xlabel="state x", title=f"{_label(g['method'])}, t = {a['times'][-1]:.2f}")
    axes[0, 0].set_ylabel("density")
    axes[0, 0].legend(fontsize=8)
    paths.append(_save(fig, out, "fpf_final_ensembles.png"))
    return paths


_COMMON = {"seed": 0, "block": 5}
# The amortised OT methods: where their maps live (None: the run directory's maps/) and the
# offline iterations of a map not stored yet (experiments/amortised.py's default).
# map_gate: the offline stage's gate (``map_for``'s ``gate``): None the experiment's (Lorenz-63 1.25),
# 0 none. The quick settings have none: their maps of 3,000 iterations would miss it and train every wave.
_MAPS = {"maps": None, "map_iterations": 21_000, "map_gate": None}

EXPERIMENTS = {
    e.name: e
    for e in (
        Experiment(
            "static", "the chapter's static example: one Bayes update, y = x^2 observation, both noise levels",
            dict(_COMMON, particles=(1000,), dim=(2,), noise=(0.4, 0.04), simulations=3, block=1,
                 methods=("enkf", "sir", "ot")),
            dict(particles=(300,), simulations=1),
            ("particles", "noise"), ("enkf", "sir", "ot", "flow_matching"), _static_cell, _static_plot,
        ),
        Experiment(
            "dynamic", "the chapter's dynamic example: MMD to the exact posterior over time",
            dict(_COMMON, particles=(1000,), dim=(2,), steps=50, simulations=20,
                 methods=("enkf", "sir", "ot", "local_ot"), **_MAPS),
            dict(particles=(200,), steps=15, simulations=2, block=2, map_iterations=3000),
            (), ("enkf", "letkf", "sir", "ot", "flow_matching", "local_ot", "local_flow") + AMORTISED_METHODS
            + LOCAL_AMORTISED_METHODS,
            _dynamic_cell, _dynamic_plot,
        ),
        Experiment(
            "dynamic-dims", "the dynamic example's MMD vs state dimension (sweep)",
            dict(_COMMON, particles=(1000,), dim=(2, 4, 6, 8, 10), steps=20, simulations=20,
                 methods=("enkf", "sir", "ot", "local_ot"), **_MAPS),
            dict(particles=(200,), dim=(2, 4), steps=12, simulations=2, block=2, map_iterations=3000),
            ("dim",), ("enkf", "letkf", "sir", "ot", "flow_matching", "local_ot", "local_flow") + LOCAL_AMORTISED_METHODS,
            _dynamic_cell,
            _dynamic_plot,
        ),
        Experiment(
            "dynamic-particles", "the dynamic example's MMD vs particle count (sweep)",
            dict(_COMMON, particles=(100, 200, 400, 800, 1600), dim=(2,), steps=20, simulations=20,
                 methods=("enkf", "sir", "ot")),
            dict(particles=(100, 400), steps=12, simulations=2, block=2),
            ("particles",), ("enkf", "sir", "ot"), _dynamic_cell, _dynamic_plot,
        ),
        Experiment(
            "lorenz63", "the chapter's Lorenz-63 experiment (x1, x3 observed): MSE over time",
            # one block of 10: the simulations shard over the CPU cores (5 + 5) in one program
            dict(_COMMON, particles=(1000,), steps=500, simulations=10, block=10,
                 methods=("enkf", "sir", "ot", "ot_enkf"), **_MAPS),
            dict(particles=(200,), steps=250, simulations=2, block=2, methods=("enkf", "sir", "ot"),
                 map_iterations=3000, map_gate=0),
            (), ("enkf", "sir", "ot", "ot_enkf") + AMORTISED_METHODS, _lorenz63_cell, _lorenz63_plot,
            minimum_steps=151,
        ),
        Experiment(
            "lorenz96", "Lorenz-96 twin experiment (DAPPER's sakov2008 setting): analysis RMSE",
            dict(_COMMON, particles=(100,), dim=(40,), steps=500, simulations=4, block=4,
                 methods=("enkf", "letkf", "sir", "ot", "local_ot")),
            dict(particles=(50,), steps=100, simulations=2, block=2,
                 methods=("enkf", "letkf", "sir", "ot", "local_ot")),
            ("dim",), ("enkf", "letkf", "sir", "ot", "local_ot", "letkf_etpf", "local_ot_etpf"), _lorenz96_cell,
            _lorenz96_plot,
        ),
        Experiment(
            "fpf-bimodal", "continuous time: feedback particle filter gains on dY = X^2 dt + dW",
            dict(_COMMON, particles=(1000,), steps=200, dt=0.01, simulations=4, block=4,
                 methods=("constant", "kernel", "learned")),
            dict(particles=(300,), steps=100, dt=0.02, simulations=2, block=2),
            (), ("constant", "kernel", "learned"), _continuous_cell, _continuous_plot,
        ),
    )
}


def blocks(num_simulations: int, block: int) -> list[int]:
    """Sizes of the simulation blocks (the last may be smaller)."""
    count = math.ceil(num_simulations / block)
    return [min(block, num_simulations - b * block) for b in range(count)]
