"""Lorenz-96 with squared observations: the localised OT filter with its shared map trained
OFFLINE (``amortised.train_local_map``) against the LETKF and the online localised OT filter.

    PYTHONPATH=.:benchmarks python benchmarks/local_amortised_l96.py [--bank-simulations 8]
        [--bank-steps 150] [--iterations 20000] [--simulations 16] [--methods a,b64]

The evaluation is ``ot_lorenz96.py``'s (n = 40, N = 100, y = x^2 + noise of std 10 every 4 RK4
steps, the runner's truths for seed 0, RMSE over the second half of 500 steps, paired with the
LETKF on the same truths). The offline stage:

1. forecasts of the LETKF's filter on ``--bank-simulations`` other truths (key 7) of
   ``--bank-steps`` steps, the first 50 dropped;
2. the local pairs of every forecast ensemble (``amortised.local_bank``) with the catalogue's
   localised update's windows, layer and context;
3. the shared networks trained on mini-batches pooled over the bank (``--batch``, f's rate
   ``--potential-rate``).

Methods: ``a``: the map used as is (no training online); ``bK``: K iterations a step from the
map (fresh optimiser states every step); ``letkf``; ``local_ot``: the catalogue's online
localised OT (64 iterations from fresh networks); ``online``: the same with ``--width`` and
``--location``. Appends to ``--out`` (JSON).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402
from ot_lorenz96 import run  # noqa: E402

from ot_filter import metrics  # noqa: E402
from ot_filter.amortised import collect_forecasts  # noqa: E402
from ot_filter.amortised.local import local_bank, train_local_map  # noqa: E402
from ot_filter.experiments._common import simulate_truths, write_text_atomic  # noqa: E402
from ot_filter.models import lorenz96  # noqa: E402
from ot_filter.runner.catalogue import LORENZ96_LOCAL, cell_key, lorenz96_local_ot, lorenz96_update  # noqa: E402


def offline_map(bank_key, train_key, template, model, iterations: int, forecasts):
    """The offline stage: ``forecasts()`` (an [E, N, n] array), their local pairs for the
    ``template`` update and its map trained ``iterations`` times. Returns ``(params, record)``:
    the bank's size, the seconds of both parts and J averaged per 1,000 iterations."""
    start = time.perf_counter()
    ensembles = forecasts()
    bank = jax.block_until_ready(local_bank(bank_key, template, model, ensembles))
    bank_seconds = time.perf_counter() - start
    start = time.perf_counter()
    params, trace = jax.block_until_ready(train_local_map(train_key, template, bank, iterations))
    train_seconds = time.perf_counter() - start
    loss = np.asarray(trace.loss)
    curve = [float(np.mean(loss[i:i + 1000])) for i in range(0, len(loss), 1000)]
    print(f"bank of {ensembles.shape[0]} ensembles in {bank_seconds:.0f} s; {iterations} iterations in "
          f"{train_seconds:.0f} s; J per 1000: {np.round(curve, 4).tolist()}", flush=True)
    return params, {"bank_ensembles": int(ensembles.shape[0]), "bank_seconds": bank_seconds,
                    "train_seconds": train_seconds, "loss_per_1000": curve}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bank-simulations", type=int, default=8)
    parser.add_argument("--bank-steps", type=int, default=150)
    parser.add_argument("--iterations", type=int, default=20_000)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--potential-rate", type=float, default=3e-4)
    parser.add_argument("--width", type=int, default=32)
    parser.add_argument("--location", action="store_true", help="location_context=True (local_ot)")
    parser.add_argument("--simulations", type=int, default=16)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--methods", default="letkf,a,b64")
    parser.add_argument("--out", default="benchmarks/results/ot_lorenz96/local_amortised.json")
    args = parser.parse_args()
    model = lorenz96(dim=40, observation_operator="square", observation_noise_std=10.0, steps_per_observation=4)
    particles = 100

    # Offline: the bank and the map.
    sizes = dict(width=args.width, location_context=args.location)
    template = lorenz96_local_ot(model, 1, warm_start=False, batch_size=args.batch,
                                 potential_learning_rate=args.potential_rate, **sizes)
    params, offline = offline_map(
        jax.random.key(8), jax.random.key(9), template, model, args.iterations,
        lambda: collect_forecasts(jax.random.key(7), model, lorenz96_update("letkf", model),
                                  num_simulations=args.bank_simulations, num_steps=args.bank_steps,
                                  num_particles=particles, burn_in=50).particles)

    truth_key, filter_key = jax.random.split(cell_key(0, 40, 0))  # the runner's truths (ot_lorenz96.py)
    states, observations = simulate_truths(truth_key, model, args.steps, args.simulations)
    keys = jax.random.split(filter_key, args.simulations)
    late = slice(args.steps // 2, None)
    record = {"setting": {k: v for k, v in vars(args).items() if k != "out"}, "local": LORENZ96_LOCAL,
              **offline, "rows": {}}
    for method in args.methods.split(","):
        if method in ("letkf", "local_ot"):
            update = method
        elif method == "online":  # the catalogue's online filter with these sizes and context
            update = lorenz96_local_ot(model, 64, warm_start=False, **sizes)
        else:
            iterations = 0 if method == "a" else int(method[1:])
            update = lorenz96_local_ot(model, iterations, warm_start=False, initial_map=params, **sizes)
        means, diverged, seconds = run(update, model, keys, observations, particles)
        rmse = np.asarray(jax.vmap(metrics.rmse)(means, states))[:, late].mean(axis=1)
        rmse = np.where(np.isfinite(rmse), rmse, np.inf)
        record["rows"][method] = dict(rmse=rmse.tolist(), mean=float(rmse.mean()),
                                      se=float(rmse.std(ddof=1) / np.sqrt(len(rmse))),
                                      fallbacks=int(diverged.sum()), seconds=seconds)
        line = f"{method}: RMSE {rmse.mean():.4f} ± {rmse.std(ddof=1) / np.sqrt(len(rmse)):.4f}"
        if "letkf" in record["rows"] and method != "letkf":
            difference = rmse - np.asarray(record["rows"]["letkf"]["rmse"])
            line += f", paired - LETKF {difference.mean():+.4f} ± {difference.std(ddof=1) / np.sqrt(len(rmse)):.4f}"
        print(f"{line}, {int(diverged.sum())} fallbacks, {seconds:.1f} s", flush=True)
    records = json.load(open(args.out)) if os.path.exists(args.out) else []
    write_text_atomic(args.out, json.dumps(records + [record], indent=1))


if __name__ == "__main__":
    main()
