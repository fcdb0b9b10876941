"""The training seed's share in an amortised map's error (issue 18): S maps of the dynamic
example (n = 2) trained together by ``train_amortised_seeds`` with the experiment's offline
settings, each filtering without online training ((a)) on the same 10 truths as
``benchmarks/amortised_ot.py``, with the map stored there for reference.

    PYTHONPATH=. python benchmarks/amortised_seeds.py [--seeds 4] [--width 64]
        [--out benchmarks/results/amortised_ot/seeds]

Writes OUT/width<W>.json: per map the EnKF's and (a)'s W1 to the exact marginals (mean over
coordinates and the worst coordinate, mean ± s.e. over the truths), their run seconds (compile
excluded, so the cost ratio is measured in one run) and the map's validation J after each round.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

from ot_filter.amortised import load_map, save_map, train_amortised_seeds
from ot_filter.experiments._common import write_text_atomic
from ot_filter.experiments.amortised import MAP_OPTIONS, OFFLINE, experiment_model
from ot_filter.experiments.dynamic_example import run_dynamic_example
from ot_filter.updates.amortised import amortised_ot

STORED = "benchmarks/results/amortised_ot/maps/dynamic-n2"


def evaluate(trained) -> dict:
    """The EnKF and (a) with ``trained`` on amortised_ot.py's truths (its key and sizes)."""
    summary = run_dynamic_example(jax.random.key(2026), dim=2, num_particles=1000, num_steps=20, num_simulations=10,
                                  methods=("enkf",), extra_updates={"amortised": amortised_ot(trained)})["metrics"]
    rows = {}
    for method in ("enkf", "amortised"):
        exact = summary[method]["exact"]
        rows[method] = dict(w1=exact["w1"]["mean"], se=exact["w1"]["stderr"], worst=exact["w1_max"]["mean"],
                            run_s=summary[method]["run_s"], diverged=summary[method].get("diverged_steps", 0))
    rows["floor"] = summary["floor"]["w1"]["mean"]
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--width", type=int, default=MAP_OPTIONS["width"])
    parser.add_argument("--out", default="benchmarks/results/amortised_ot/seeds")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    results = {}
    if args.width == MAP_OPTIONS["width"] and os.path.exists(os.path.join(STORED, "map.json")):
        results["stored"] = evaluate(load_map(STORED))
        print("stored map:", results["stored"], flush=True)
    started = time.perf_counter()
    maps, histories = train_amortised_seeds(
        jax.random.split(jax.random.key(180), args.seeds), experiment_model("dynamic", 2), model_name="dynamic-n2",
        num_particles=1000, **OFFLINE["dynamic"], **dict(MAP_OPTIONS, width=args.width))
    results["training_s"] = time.perf_counter() - started
    print(f"{args.seeds} seeds trained in {results['training_s']:.0f} s", flush=True)
    for seed, trained in enumerate(maps):
        save_map(os.path.join(args.out, "maps", f"width{args.width}-seed{seed}"), trained)
        row = evaluate(trained)
        row["validation"] = [float(history.validation_loss[-1]) for history in histories[seed]]
        results[f"seed{seed}"] = row
        print(f"seed {seed}:", row, flush=True)
    write_text_atomic(os.path.join(args.out, f"width{args.width}.json"), json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
