"""The chapter's dynamic example at n = 10: the localised OT filter with its shared map trained
OFFLINE (``amortised.train_local_map``) against the online localised filter and the EnKF, by
W1 per coordinate to the exact grid filter.

    PYTHONPATH=.:benchmarks python benchmarks/local_amortised_dynamic.py [--dim 10] [--simulations 10]
        [--bank-simulations 4] [--iterations 20000] [--methods enkf,online,a]

Coordinates are independent and observed one by one (windows of radius 0): every coordinate's
local problem at every step is the same kind of problem, which is what one offline map can
learn. The bank: the online localised filter's forecasts on ``--bank-simulations`` other truths
(20 steps each). ``online``: the localised filter with the dynamic experiment's OT settings
(width 64, 1024 -> 64 iterations, f's rate 3e-4); ``a``: the offline map used as is (one forward
pass a step); ``bK``: K iterations a step from the map. N = 1000, 20 steps, W1 averaged over
t >= 1 and the coordinates, with its N-sample floor. Appends to ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from local_amortised_l96 import offline_map

import ot_filter as otf
from ot_filter.amortised import collect_forecasts
from ot_filter.experiments._common import diverged_flags, simulate_truths, write_text_atomic
from ot_filter.experiments.dynamic_example import dynamic_model, exact_comparison, exact_floor, exact_posteriors
from ot_filter.localisation import local_windows

PARTICLES, STEPS = 1000, 20


LABELS = {"enkf": "EnKF", "online": "localised OT, online (1024 -> 64 a step)",
          "a": "(a) offline map, no training online", "b64": "(b) 64 iterations a step from the map"}


def plot(records, path):
    """One group of bars per record (n and bank), W1 ± s.e. per method, the floor dotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    methods = [m for m in LABELS if any(m in r["rows"] for r in records)]
    width = 0.8 / len(methods)
    for i, method in enumerate(methods):
        xs = [g + (i - (len(methods) - 1) / 2) * width for g, r in enumerate(records) if method in r["rows"]]
        rows = [r["rows"][method] for r in records if method in r["rows"]]
        bars = ax.bar(xs, [row["w1"] for row in rows], width, yerr=[row["se"] for row in rows], capsize=3,
                      label=LABELS[method])
        ax.bar_label(bars, labels=[f"{row['w1']:.3f}" for row in rows], fontsize=7, padding=2)
    for g, r in enumerate(records):
        ax.hlines(r["floor_w1"], g - 0.45, g + 0.45, colors="k", linestyles=":", lw=1)
    ax.set_xticks(range(len(records)),
                  [f"n = {r['setting']['dim']}\nbank of {r['bank_ensembles']} ensembles" for r in records])
    ax.set_yscale("log")
    ax.set_ylabel("W1 per coordinate to the exact filter (mean over t >= 1)")
    ax.set_title("Dynamic example, N = 1000, 10 simulations: the localised OT filter with an offline map\n"
                 "(dotted: the N-sample floor)", fontsize=10)
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(axis="y", alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dim", type=int, default=10)
    parser.add_argument("--simulations", type=int, default=10)
    parser.add_argument("--bank-simulations", type=int, default=4)
    parser.add_argument("--iterations", type=int, default=20_000)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--methods", default="enkf,online,a")
    parser.add_argument("--out", default="benchmarks/results/amortised_ot/local_dynamic.json")
    parser.add_argument("--plot", default=None, help="draw the records of --out into this PNG instead")
    args = parser.parse_args()
    if args.plot:
        return plot(json.load(open(args.out)), args.plot)
    model = dynamic_model(args.dim)
    windows = local_windows(model.geometry, 0.0)
    sizes = dict(width=64)

    def online():
        # batches of 128: the recorded runs' (local_ot's default until 0.2.19)
        return otf.local_ot(windows, num_iterations=(1024, 64), potential_optimizer=optax.adamw(3e-4, weight_decay=1.0),
                            batch_size=128, **sizes)

    template = otf.local_ot(windows, batch_size=args.batch, potential_learning_rate=3e-4, **sizes)
    params, offline = offline_map(
        jax.random.key(13), jax.random.key(14), template, model, args.iterations,
        lambda: collect_forecasts(jax.random.key(12), model, online(), num_simulations=args.bank_simulations,
                                  num_steps=STEPS, num_particles=PARTICLES).particles)

    _, observations = simulate_truths(jax.random.key(11), model, STEPS, args.simulations)
    reference = exact_posteriors(observations)
    floor = exact_floor(jax.random.key(15), PARTICLES, reference)["floor_w1"][:, 1:].mean()
    record = {"setting": {k: v for k, v in vars(args).items() if k != "out"}, **offline,
              "floor_w1": float(floor), "rows": {}}
    print(f"floor W1 {float(floor):.4f}", flush=True)
    for method in args.methods.split(","):
        if method == "enkf":
            update = otf.enkf()
        elif method == "online":
            update = online()
        else:
            update = otf.local_ot(windows, num_iterations=0 if method == "a" else int(method[1:]), warm_start=False,
                                  initial_map=params, batch_size=128, **sizes)
        keys = jax.random.split(jax.random.key(16), args.simulations)

        def one(key, y, update=update):
            result = otf.run_filter(key, model, update, y, PARTICLES, save_every=1)
            diverged = diverged_flags(result.info)
            return result.particles, result.log_weights, jnp.zeros(y.shape[0], bool) if diverged is None else diverged

        run = jax.jit(jax.vmap(one))
        compiled = run.lower(keys, observations).compile()
        start = time.perf_counter()
        particles, log_weights, diverged = jax.block_until_ready(compiled(keys, observations))
        seconds = time.perf_counter() - start
        w1 = np.asarray(exact_comparison(jax.random.key(15), particles, log_weights, reference)["w1"])[:, 1:]
        per_simulation = w1.mean(axis=(1, 2))
        record["rows"][method] = dict(w1=float(per_simulation.mean()),
                                      se=float(per_simulation.std(ddof=1) / np.sqrt(len(per_simulation))),
                                      worst_coordinate=float(w1.mean(axis=1).max(axis=1).mean()),
                                      fallbacks=int(np.sum(np.asarray(diverged) > 0)), seconds=seconds)
        print(f"{method}: {record['rows'][method]}", flush=True)
    records = json.load(open(args.out)) if os.path.exists(args.out) else []
    write_text_atomic(args.out, json.dumps(records + [record], indent=1))


if __name__ == "__main__":
    main()
