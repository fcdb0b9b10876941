"""Record of 2026-12-07: variants of the global map's training on the static example at n = 10
(a diagnostic patch of ``updates/ot.py``, not in the library).

    PYTHONPATH=.:benchmarks python benchmarks/results/ot_dimension_size_rule/objective_variants.py \
        --tag NAME [--energy-weight A] [--energy-only] [--marginal-weight B] \
        [--potential-width W] [--transport-width W] [--seeds 0,1] [--key 0]

One update of ``benchmarks/averaged_maps.py`` (the README table's two prior samples, training key
0, N = 1000), with T's loss or the networks changed:

- ``--energy-weight A``: T's loss is the chapter's c(xbar, T) - f(T) plus A times the energy
  score of the map's conditional samples, E|T(xbar, y) - x| - E|T(xbar, y) - T(xbar', y)| / 2
  over the joint pairs (x, y), with two independent copies xbar, xbar'. The energy score is a
  strictly proper scoring rule: it is least where T(., y) pushes the prior to the posterior, as
  the saddle's T* does, so the chapter's solution stays a minimiser of the sum.
- ``--energy-only``: T trained on the energy score alone (no f, no adversary); the loss test of
  the divergence check is off (J of an untrained f means nothing), the other tests stay.
  ``--marginal-weight B`` adds B times the sum of the coordinates' 1-D energy scores (CRPS).
- ``--potential-width`` / ``--transport-width``: f's or T's width alone (the rule gives both 64).

Prints one JSON row per prior sample (W1 per coordinate to the exact posterior, the floor of N
exact samples, seconds on one core).
"""

import argparse
import importlib
import json
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import optax  # noqa: E402

import ot_filter.transport.saddle as saddle  # noqa: E402
from ot_filter.transport.networks import PotentialNetwork, TransportNetwork  # noqa: E402

OT = importlib.import_module("ot_filter.updates.ot")  # the module (the package exports the function ``ot``)


def energy_score(moved, moved2, x, marginal_weight):
    """Energy score of the two conditional samples ``moved``, ``moved2`` against ``x`` (rows),
    plus ``marginal_weight`` times the coordinates' 1-D scores."""
    def distance(a, b):
        return jnp.sqrt(jnp.sum((a - b) ** 2, -1) + 1e-12)
    joint = 0.5 * (distance(moved, x) + distance(moved2, x)) - 0.5 * distance(moved, moved2)
    marginal = jnp.sum(0.5 * (jnp.abs(moved - x) + jnp.abs(moved2 - x)) - 0.5 * jnp.abs(moved - moved2), -1)
    return jnp.mean(joint) + marginal_weight * jnp.mean(marginal)


def patched_train_saddle(args):
    """``saddle.train_saddle`` with T's loss changed as ``args`` says."""

    def train_saddle(key, state, sample_batch, num_iterations, *, potential_net, transport_net,
                     potential_optimizer, transport_optimizer, inner_steps, enkf_layer, record_length,
                     cost_from_layer=False):
        def potential(p):
            return lambda x, y: potential_net.apply(p, x, y)

        def transport(p):
            return lambda x, y: transport_net.apply(p, x, y)

        def transport_loss(tp, pp, batch, gain):
            moved, cost = saddle.transport_cost(transport(tp), batch, gain, cost_from_layer)
            other = batch._replace(xbar=jnp.roll(batch.xbar, 1, 0), ybar=jnp.roll(batch.ybar, 1, 0))
            moved2, _ = saddle.transport_cost(transport(tp), other, gain, cost_from_layer)
            score = energy_score(moved, moved2, batch.x, args.marginal_weight)
            if args.energy_only:
                return score
            y = saddle.conditioning(batch.y, batch.context)
            return jnp.mean(cost - potential(pp)(moved, y)) + args.energy_weight * score

        def objective(pp, tp, batch, gain):
            return saddle.saddle_objective(potential(pp), transport(tp), batch, gain, cost_from_layer)

        def outer(it, carry):
            state, loss, smoothed, finite = carry
            batch = sample_batch(jax.random.fold_in(key, it))
            gain = saddle.batch_gain(batch, enkf_layer)
            params = state.params

            def inner(_, c):
                tp, opt = c
                grads = jax.grad(transport_loss)(tp, params.potential, batch, gain)
                updates, opt = transport_optimizer.update(grads, opt, tp)
                return optax.apply_updates(tp, updates), opt

            tp, tos = jax.lax.fori_loop(0, inner_steps, inner, (params.transport, state.transport_opt_state))
            value, grads = jax.value_and_grad(objective)(params.potential, tp, batch, gain)
            if args.energy_only:
                pp, pos = params.potential, state.potential_opt_state
            else:
                updates, pos = potential_optimizer.update(jax.tree.map(jnp.negative, grads),
                                                          state.potential_opt_state, params.potential)
                pp = optax.apply_updates(params.potential, updates)
            state = saddle.TrainingState(saddle.SaddleParams(pp, tp), pos, tos)
            loss = loss.at[it].set(value, mode="drop")
            smoothed = jnp.where(it == 0, value,
                                 saddle.LOSS_SMOOTHING * smoothed + (1 - saddle.LOSS_SMOOTHING) * value)
            return state, loss, smoothed, finite & jnp.isfinite(value)

        dtype = jax.tree.leaves(state.params)[0].dtype
        carry = (state, jnp.full((record_length,), jnp.inf, dtype), jnp.zeros((), dtype), jnp.array(True))
        state, loss, smoothed, finite = jax.lax.fori_loop(0, num_iterations, outer, carry)
        return state, saddle.TrainingTrace(jnp.where(jnp.isfinite(loss), loss, jnp.inf), smoothed, finite)

    return train_saddle


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tag", required=True)
    parser.add_argument("--energy-weight", type=float, default=0.0)
    parser.add_argument("--energy-only", action="store_true")
    parser.add_argument("--marginal-weight", type=float, default=0.0)
    parser.add_argument("--potential-width", type=int)
    parser.add_argument("--transport-width", type=int)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--key", type=int, default=0)
    args = parser.parse_args()

    OT.train_saddle = patched_train_saddle(args)
    if args.energy_only:
        OT.divergence_test = lambda finite, smoothed, *rest: jnp.array(False)
    if args.potential_width or args.transport_width:
        def networks(structure):
            return (PotentialNetwork(args.potential_width or structure.width, structure.num_blocks, structure.activation),
                    TransportNetwork(args.transport_width or structure.width, structure.num_blocks, structure.activation))
        OT.networks = networks

    import averaged_maps  # benchmarks/: the static example over training keys
    run = averaged_maps.build(10, "ot")
    seed_keys = jax.random.split(jax.random.key(2026), 2)
    for seed in map(int, args.seeds.split(",")):
        start = time.perf_counter()
        w1, floor, diverged = jax.block_until_ready(run(seed_keys[seed], args.key))
        print(json.dumps({"tag": args.tag, "seed": seed, "key": args.key, "w1": float(w1.mean()),
                          "w1_max": float(w1.max()), "floor": float(floor.mean()),
                          "ratio": float(w1.mean() / floor.mean()), "diverged": bool(diverged),
                          "seconds": round(time.perf_counter() - start, 1)}), flush=True)


if __name__ == "__main__":
    main()
