"""The chapter's static example: one Bayes update with a bimodal posterior.

    X ~ N(0, I_n),   Y = 0.5 X (.) X + lambda_w W,   condition on y = (1, ..., 1).

Each coordinate's posterior has modes at +-sqrt(2) and is computed exactly on a fine grid
(``ot_filter.reference``). Every method updates the SAME prior particles; we measure per seed:

- W1 between each coordinate's posterior particles and the exact posterior (averaged over
  coordinates), with the W1 of N i.i.d. exact samples as the Monte-Carlo floor;
- the mass on the positive mode per coordinate (exact: 1/2 by symmetry);
- for OT, the consistency condition: MMD between the transported joint sample
  (T(Xbar^j, Y^s(j)), Y^s(j)) (s a random permutation) and a fresh sample of P_XY of the same
  size, against the MMD between two fresh independent samples of P_XY;
- for OT, the training diagnostics (divergence, c-concavity).

A run "holds both modes" when every coordinate's positive mass is within 0.5 +- 0.1.
"""

from __future__ import annotations

import os
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter import metrics
from ot_filter.models import squared_observation
from ot_filter.reference import squared_observation_posterior
from ot_filter.experiments._common import METHODS, compile_and_run, make_updates, methods_present, save_figure, stats
MODE_TOLERANCE = 0.1


def run_static_example(
    key: jax.Array,
    noise: float = 0.4,
    num_particles: int = 1000,
    num_seeds: int = 3,
    dim: int = 2,
    observation: float = 1.0,
    methods: Sequence[str] = METHODS,
    ot_options: dict | None = None,
    keep_particles: int = 1,
) -> dict:
    """Runs every method on ``num_seeds`` independent prior samples (vmapped) and measures them.

    Returns a dict of plain Python numbers and lists (JSON-ready) under ``"metrics"`` and NumPy
    arrays for figures under ``"arrays"`` (the first ``keep_particles`` seeds).
    """
    model = squared_observation(dim=dim, noise=noise, observation_scale=0.5, static=True)
    # Localised methods are told that the coordinates are independent (radius 0: own y only).
    updates = make_updates(methods, ot_options, model=model, radius=0.0)
    y = jnp.full((dim,), observation)
    exact = squared_observation_posterior(observation, noise, scale=0.5)
    grid = exact.grid
    masses = jnp.broadcast_to(exact.density, (dim,) + exact.density.shape)

    def draw_joint(draw_key):
        state_key, observation_key = jax.random.split(draw_key)
        x = jax.vmap(model.sample_initial)(jax.random.split(state_key, num_particles))
        ys = jax.vmap(model.sample_observation)(jax.random.split(observation_key, num_particles), x)
        return x, ys

    def one_seed(seed_key, grid, masses):
        # grid and masses are arguments, not constants: XLA would constant-fold their CDFs.
        def compare(compare_key, samples):
            return metrics.compare_to_product_grid(compare_key, samples, None, grid, masses, num_particles)

        prior_key, update_key, check_key, floor_key, compare_key = jax.random.split(seed_key, 5)
        prior = jax.vmap(model.sample_initial)(jax.random.split(prior_key, num_particles))
        # N exact samples scored like a method: the Monte-Carlo floor of every metric at this N.
        floor = compare(compare_key, metrics.product_grid_sample(floor_key, grid, masses, num_particles))
        out = {"prior": prior, "floor_w1": floor.w1, "floor_sliced_w2": floor.sliced_w2,
               "floor_energy": floor.energy}
        for index, (name, update) in enumerate(updates.items()):
            init_key, apply_key = jax.random.split(jax.random.fold_in(update_key, index))
            state = update.init(init_key, prior, model)
            posterior, state, info = update.apply(apply_key, state, prior, y, model)
            comparison = compare(compare_key, posterior)
            entry = {
                "posterior": posterior,
                "w1": comparison.w1,
                "sliced_w2": comparison.sliced_w2,
                "energy": comparison.energy,
                "positive_mass": jnp.mean(posterior > 0, axis=0),
                "finite": jnp.all(jnp.isfinite(posterior)),
            }
            if name == "ot":
                perm_key, fresh_key, fresh2_key = jax.random.split(check_key, 3)
                simulated = state.simulated_observations
                paired_y = simulated[jax.random.permutation(perm_key, num_particles)]
                moved = update.transport(state, prior, paired_y)
                fresh_x, fresh_y = draw_joint(fresh_key)
                other_x, other_y = draw_joint(fresh2_key)
                fresh = jnp.concatenate([fresh_x, fresh_y], axis=1)
                bandwidth = metrics.median_bandwidth(fresh, jnp.concatenate([other_x, other_y], 1))
                entry.update(
                    joint_mmd=metrics.mmd(jnp.concatenate([moved, paired_y], 1), fresh, bandwidth),
                    reference_joint_mmd=metrics.mmd(jnp.concatenate([other_x, other_y], 1), fresh, bandwidth),
                    transported_joint=jnp.concatenate([moved, paired_y], 1),
                    joint=jnp.concatenate([prior, simulated], 1),
                    diverged=info.diverged,
                    final_loss=info.final_loss,
                    min_hessian_eigenvalue=info.min_hessian_eigenvalue,
                    concavity_violation=info.concavity_violation,
                    loss=info.loss,
                )
            out[name] = entry
        return out

    seed_keys = jax.random.split(key, num_seeds)
    results, timing = compile_and_run(jax.vmap(one_seed, in_axes=(0, None, None)), seed_keys, grid, masses,
                                      shard=False)
    output = _summarise(results, methods, noise, num_particles, num_seeds, dim, observation, exact,
                        keep_particles)
    output["metrics"].update(timing)  # compile_s and run_s, measured separately
    return output


def _summarise(results, methods, noise, num_particles, num_seeds, dim, observation, exact, keep):
    summary = {
        "noise": noise, "num_particles": num_particles, "num_seeds": num_seeds, "dim": dim,
        "observation": observation,
        "floor_w1": stats(results["floor_w1"].mean(axis=1)),
        "floor_w1_max": stats(results["floor_w1"].max(axis=1)),
        "floor_sliced_w2": stats(results["floor_sliced_w2"]),
        "floor_energy": stats(results["floor_energy"]),
        "exact_grid_edge_mass": float(exact.edge_mass),
    }
    arrays = {"prior": results["prior"][:keep], "grid": np.asarray(exact.grid),
              "density": np.asarray(exact.density)}
    for name in methods:
        entry = results[name]
        w1 = entry["w1"].mean(axis=1)  # [seeds]
        holds = np.all(np.abs(entry["positive_mass"] - 0.5) <= MODE_TOLERANCE, axis=1)
        method = {
            "w1": stats(w1),
            "w1_per_seed": w1.round(4).tolist(),
            "w1_max": stats(entry["w1"].max(axis=1)),  # the worst coordinate: a lost mode shows
            "sliced_w2": stats(entry["sliced_w2"]),
            "energy": stats(entry["energy"]),
            "positive_mass_per_seed": entry["positive_mass"].round(3).tolist(),
            "seeds_holding_both_modes": int(holds.sum()),
            "all_finite": bool(entry["finite"].all()),
        }
        if name == "ot":
            method.update(
                diverged_seeds=int(entry["diverged"].sum()),
                final_loss=stats(entry["final_loss"]),
                min_hessian_eigenvalue=stats(entry["min_hessian_eigenvalue"]),
                concavity_violation=stats(entry["concavity_violation"]),
                joint_mmd=stats(entry["joint_mmd"]),
                reference_joint_mmd=stats(entry["reference_joint_mmd"]),
            )
            arrays["ot_transported_joint"] = entry["transported_joint"][:keep]
            arrays["ot_joint"] = entry["joint"][:keep]
            arrays["ot_loss"] = entry["loss"][:keep]
        summary[name] = method
        arrays[f"{name}_posterior"] = entry["posterior"][:keep]
    if "ot" in methods:
        others = [name for name in methods if name != "ot"]
        ot_w1 = results["ot"]["w1"].mean(axis=1)
        ot_holds = np.all(np.abs(results["ot"]["positive_mass"] - 0.5) <= MODE_TOLERANCE, axis=1)
        beats = np.ones_like(ot_holds)
        for name in others:
            beats &= ot_w1 < results[name]["w1"].mean(axis=1)
        summary["ot_beats_others_per_seed"] = int(beats.sum())
        summary["ot_success_seeds"] = int((beats & ot_holds).sum())
    return {"metrics": summary, "arrays": arrays}


def plot_static_example(result: dict, out_dir: str, tag: str = "") -> list[str]:
    """Writes the chapter's figures for one ``run_static_example`` result; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    arrays, summary = result["arrays"], result["metrics"]
    label = f"lambda_w = {summary['noise']}, N = {summary['num_particles']}"
    tag = tag or f"noise{summary['noise']}_N{summary['num_particles']}"
    paths = []

    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    prior = arrays["prior"][0]
    ax.scatter(prior[:, 0], prior[:, 1], s=4, alpha=0.5)
    ax.set(xlabel="$x_1$", ylabel="$x_2$", title=f"Prior samples ({label})", aspect="equal")
    paths.append(save_figure(fig, out_dir, f"prior_{tag}.png"))

    if "ot_joint" in arrays:
        dim = prior.shape[1]
        fig, axes = plt.subplots(1, dim, figsize=(4.5 * dim, 4), squeeze=False)
        for k in range(dim):
            ax = axes[0, k]
            joint, moved = arrays["ot_joint"][0], arrays["ot_transported_joint"][0]
            ax.scatter(joint[:, k], joint[:, dim + k], s=4, alpha=0.5, label="$(X, Y) \\sim P_{XY}$")
            ax.scatter(moved[:, k], moved[:, dim + k], s=4, alpha=0.5, label="$(T(\\bar X, Y), Y)$")
            ax.set(xlabel=f"$x_{k + 1}$", ylabel=f"$y_{k + 1}$", title=f"Joint samples, coordinate {k + 1}")
            ax.legend(loc="upper center", fontsize=8, markerscale=3)
        fig.suptitle(f"OT consistency check ({label})")
        paths.append(save_figure(fig, out_dir, f"joint_{tag}.png"))

    methods = methods_present(name[:-len("_posterior")] for name in arrays if name.endswith("_posterior"))
    fig, axes = plt.subplots(1, len(methods), figsize=(4.2 * len(methods), 3.6), squeeze=False, sharey=True)
    for ax, name in zip(axes[0], methods):
        samples = arrays[f"{name}_posterior"][0][:, 0]
        ax.hist(samples, bins=60, range=(-3, 3), density=True, alpha=0.6, label=f"{name.upper()} particles")
        ax.plot(arrays["grid"], arrays["density"], "k", lw=1.2, label="exact posterior")
        title = f"{name.upper()}: W1 {summary[name]['w1']['mean']:.3f}"
        if summary["num_seeds"] > 1:
            title += f" (mean of {summary['num_seeds']} runs)"
        ax.set(xlim=(-3, 3), xlabel="$x_1$", title=title)
        ax.legend(fontsize=8)
    axes[0, 0].set_ylabel("density")
    fig.suptitle(f"Posterior of $x_1$ given y = {summary['observation']} ({label}; particles of the first run)")
    paths.append(save_figure(fig, out_dir, f"posterior_{tag}.png"))
    return paths

