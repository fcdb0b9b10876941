"""Does the global map at n = 10 overfit its N = 1,000 particles as it trains? Its error over the
iterations, on its own particles and on fresh ones (what early stopping could gain at best).

    PYTHONPATH=.:benchmarks python benchmarks/ot_training_curve.py [--dim 10] [--train 1000]
        [--chunk 1000] [--chunks 20] [--seed 0] [--options '{}'] [--potential-optimizer SPEC] [--out FILE]
    PYTHONPATH=.:benchmarks python benchmarks/ot_training_curve.py --plot FIGURE.png [--out FILE]

Static example (lambda_w = 0.4, y = 1), the prior sample of seed ``--seed`` of
``benchmarks/ot_sample_size.py`` (key 2026 split in 2: its records' prior samples, fresh
particles and floors). One ``ot()`` (its defaults unless ``--options``) is trained in
``--chunks`` warm-started updates of ``--chunk`` iterations on the same prior and observation:
the optimiser states carry over (the filter's innovation trend does not: ``build``), so this is
one training of chunks x chunk iterations, scored
after each chunk by W1 per coordinate to the exact posterior (mean and worst coordinate) of

- its own particles transported (what the static example and the filters score), beside the W1 of
  as many exact samples (the floor at that size);
- 10,000 fresh prior particles transported by the same map (floor about 0.011): the map's own
  error, which rises with the iterations if the map fits its particles rather than their law.

``--average K`` also scores, after each chunk, T's parameters averaged uniformly over the last K
chunk ends (the map an average of iterates would give; the training goes on from the last one).

``--potential-optimizer`` replaces f's AdamW (3e-4, weight decay 1) by another optax optimiser
with the same rate and decoupled weight decay (``potential_optimizer``): ``optimistic:o`` is
optax's optimistic Adam with optimism o times the rate (a cure for limit cycles in min-max games),
``adamw-b1:b`` AdamW with first-moment decay b (GANs' 0.5 or 0: less momentum to circle with).

Appends one record per run to ``--out`` (JSON list). ``--plot`` draws the records of ``--out``
instead: one panel per setting (the seeds overlaid), W1 against the iterations with the floors.
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
from ot_sample_size import NOISE, OBSERVATION, SCALE, draws, exact_scoring

import ot_filter as otf
from ot_filter.experiments._common import write_text_atomic
from ot_filter.models import squared_observation


def potential_optimizer(spec: str, learning_rate: float = 3e-4, weight_decay: float = 1.0):
    """f's optimiser from ``--potential-optimizer`` (module docstring), with AdamW's decoupled decay."""
    name, _, value = spec.partition(":")
    if name == "optimistic":
        base = optax.optimistic_adam(learning_rate, optimism=float(value or 1) * learning_rate)
        # AdamW's decay, -rate * decay * params, added to the scaled update.
        return optax.chain(base, optax.add_decayed_weights(-learning_rate * weight_decay))
    if name == "adamw-b1":
        return optax.adamw(learning_rate, b1=float(value), weight_decay=weight_decay)
    raise ValueError(f"--potential-optimizer: unknown {spec!r}")


def build(*, dim, num_train, num_evaluate, options, chunk, optimizer=None):
    """``(setup, step)``: ``setup(key)`` draws what ``ot_sample_size.py`` draws for that key (the
    prior, the fresh particles and their observations, the two floors) and initialises the
    update; ``step(key, state, ...)`` trains one chunk and scores it."""
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=SCALE, static=True)
    update = otf.ot(**dict(options, num_iterations=chunk), potential_optimizer=optimizer)
    w1, exact_samples = exact_scoring(dim)
    y = jnp.full((dim,), OBSERVATION)

    @jax.jit
    def setup(key):
        d = draws(key, model, num_train, num_evaluate)
        floors = {"floor_in_sample": w1(exact_samples(d.floor_key, num_train)),
                  "floor_out_of_sample": w1(exact_samples(d.floor2_key, num_evaluate))}
        return d.apply_key, update.init(d.init_key, d.prior, model), d.prior, d.fresh, d.simulated, floors

    @jax.jit
    def score(state, transport, prior, fresh, simulated):
        """W1 of the prior and of the fresh particles moved by the map ``transport``."""
        training = state.training._replace(params=state.training.params._replace(transport=transport))
        state = state._replace(training=training)
        return w1(update.transport(state, prior, y)), w1(update.transport(state, fresh, y, simulated))

    @jax.jit
    def step(key, state, prior, fresh, simulated):
        # The same y at every chunk would drive the filter's innovation trend (a moving average
        # over updates) below its floor after about 15 chunks, and the update would then stop
        # training as a filter that lost track: each chunk starts it afresh (at 1).
        state = state._replace(innovation_trend=jnp.ones_like(state.innovation_trend))
        posterior, state, info = update.apply(key, state, prior, y, model)
        moved = update.transport(state, fresh, y, simulated)
        return state, {"in_sample": w1(posterior), "out_of_sample": w1(moved), "diverged": info.diverged}

    return setup, step, score


def plot(records, path):
    """W1 over the iterations: one panel per setting, the seeds overlaid, with the floors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settings = sorted({json.dumps(r["options"], sort_keys=True) for r in records}, key=lambda s: (len(s), s))
    columns = min(2, len(settings))
    rows = -(-len(settings) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(6 * columns, 4 * rows), sharey=True, squeeze=False)
    for ax in axes.flat[len(settings):]:
        ax.set_visible(False)
    for ax, setting in zip(axes.flat, settings):
        for r in (r for r in records if json.dumps(r["options"], sort_keys=True) == setting):
            iterations = [p["iterations"] for p in r["curve"]]
            line, = ax.plot(iterations, [p["in_sample"] for p in r["curve"]], "-o", ms=3,
                            label=f"seed {r['seed']}: its {r['train']:,} particles")
            ax.plot(iterations, [p["out_of_sample"] for p in r["curve"]], "--s", ms=3, color=line.get_color(),
                    label=f"seed {r['seed']}: {r['evaluate']:,} fresh particles")
            ax.axhline(r["floor_in_sample"], color=line.get_color(), lw=0.8, ls=":")
            ax.axhline(2 * r["floor_in_sample"], color="k", lw=0.8, ls="-.")
        options = json.loads(setting)
        ax.set(xlabel="outer iterations (one f step each)",
               title=f"n = {r['dim']}, " + (", ".join(f"{k} {v}" for k, v in options.items()) or "ot() defaults"))
        ax.grid(alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("W1 per coordinate to the exact posterior (mean)")
    axes[0, 0].legend(fontsize=7, title="dotted: N-sample floor; dash-dot: twice it", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dim", type=int, default=10)
    parser.add_argument("--train", type=int, default=1000, help="prior particles the map learns from")
    parser.add_argument("--evaluate", type=int, default=10_000, help="fresh particles it is scored on")
    parser.add_argument("--chunk", type=int, default=1000, help="iterations between two scores")
    parser.add_argument("--chunks", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0, help="which of ot_sample_size.py's 2 seeds")
    parser.add_argument("--options", default="{}", help="ot() options as JSON (not num_iterations)")
    parser.add_argument("--potential-optimizer", default=None, help="f's optimiser (module docstring)")
    parser.add_argument("--average", type=int, default=0, help="also score the mean of the last K chunk ends' T")
    parser.add_argument("--out", default="benchmarks/results/ot_dimension_size_rule/training_curve.json")
    parser.add_argument("--plot", default=None, help="draw the records of --out into this PNG instead")
    args = parser.parse_args()
    if args.plot:
        return plot(json.load(open(args.out)), args.plot)
    options = json.loads(args.options)
    optimizer = None
    if args.potential_optimizer:
        optimizer = potential_optimizer(args.potential_optimizer, options.get("potential_learning_rate", 3e-4),
                                         options.get("potential_weight_decay", 1.0))
    setup, step, score = build(dim=args.dim, num_train=args.train, num_evaluate=args.evaluate, options=options,
                               chunk=args.chunk, optimizer=optimizer)
    if args.potential_optimizer:  # recorded with the options: the plot's panels are per setting
        options = dict(options, potential_optimizer=args.potential_optimizer)
    if args.average:
        options = dict(options, average=args.average)
    apply_key, state, prior, fresh, simulated, floors = setup(jax.random.split(jax.random.key(2026), 2)[args.seed])
    record = {"dim": args.dim, "train": args.train, "evaluate": args.evaluate, "options": options,
              "chunk": args.chunk, "seed": args.seed, "device": str(jax.devices()[0]),
              **{name: float(np.mean(value)) for name, value in floors.items()}, "curve": []}
    print(json.dumps({k: v for k, v in record.items() if k != "curve"}), flush=True)
    ends = []  # T at the last chunk ends (--average)
    for chunk in range(args.chunks):
        start = time.perf_counter()
        state, out = jax.block_until_ready(step(jax.random.fold_in(apply_key, chunk), state, prior, fresh, simulated))
        point = {"iterations": (chunk + 1) * args.chunk, "seconds": round(time.perf_counter() - start, 1),
                 "diverged": bool(out["diverged"])}
        for name in ("in_sample", "out_of_sample"):
            point[name] = float(np.mean(out[name]))
            point[name + "_worst"] = float(np.max(out[name]))
        if args.average:
            ends = (ends + [state.training.params.transport])[-args.average:]
            mean = jax.tree.map(lambda *leaves: sum(leaves) / len(leaves), *ends)
            own, moved = score(state, mean, prior, fresh, simulated)
            point.update(averaged_in_sample=float(np.mean(own)), averaged_in_sample_worst=float(np.max(own)),
                         averaged_out_of_sample=float(np.mean(moved)))
        print(json.dumps(point), flush=True)
        record["curve"].append(point)
    records = json.load(open(args.out)) if os.path.exists(args.out) else []
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    write_text_atomic(args.out, json.dumps(records + [record], indent=1))


if __name__ == "__main__":
    main()
