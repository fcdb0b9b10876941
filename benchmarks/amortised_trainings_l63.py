"""How much one offline training of a Lorenz-63 amortised map decides (a)'s error, and what
averaging takes off (issue 18: (a) within 25 % of the online OT filter).

    PYTHONPATH=.:benchmarks python benchmarks/amortised_trainings_l63.py train --observed 0,2 --seeds 4 --key 300
        [--options '{"average_chunks": 20, "average_rounds": "last"}'] --out DIR
    PYTHONPATH=.:benchmarks python benchmarks/amortised_trainings_l63.py score --observed 0,2
        --maps DIR/seed0,DIR/seed1 [--filter-keys 0,1,2] [--truths-key 2026] --record FILE.json

``train``: S trainings of the experiment's map (``offline_options`` and ``map_options`` of
Lorenz-63, ``--options`` on top: e.g. ``{"average_chunks": 0}`` for the last iterate, the
settings before 2026-12-06) from ``split(key(--key), S)``, trained together
(``train_amortised_seeds``), stored in ``DIR/seedS``. ``score``: each map's filter (a) on the
table's truths (``amortised_warm_from.score``: MSE of the mean to the truth after t = 1.5, 10
simulations, no exact posterior), every map on the same filter keys (paired). The averages of
several trainings are ``benchmarks/amortised_distil.py --map DIR/seed0 --teachers DIR/seed1``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

from amortised_warm_from import TRUTHS_KEY, score  # noqa: E402
from ot_filter.amortised import load_map, save_map, train_amortised_seeds  # noqa: E402
from ot_filter.experiments._common import write_text_atomic  # noqa: E402
from ot_filter.experiments.amortised import experiment_model, map_name, map_options, offline_options  # noqa: E402
from ot_filter.updates.amortised import amortised_ot  # noqa: E402


def train(args, observed) -> None:
    # --options override the experiment's (a plain dict(**a, **b) refuses a key given twice)
    options = {**offline_options("lorenz63", 3), **map_options(3, "lorenz63"), **json.loads(args.options)}
    print(options, flush=True)
    started = time.perf_counter()
    maps, histories = train_amortised_seeds(
        jax.random.split(jax.random.key(args.key), args.seeds), experiment_model("lorenz63", 3, observed),
        model_name=map_name("lorenz63", 3, observed), num_particles=1000, **options)
    print(f"{args.seeds} trainings in {time.perf_counter() - started:.0f} s", flush=True)
    for seed, trained in enumerate(maps):
        save_map(os.path.join(args.out, f"seed{seed}"), trained)
        print(seed, "validation J after each round:", [float(h.validation_loss[-1]) for h in histories[seed]],
              flush=True)


def score_maps(args, observed) -> None:
    record = json.load(open(args.record)) if os.path.exists(args.record) else {}
    for path in args.maps.split(","):
        update = amortised_ot(load_map(path))
        for filter_key in (int(k) for k in args.filter_keys.split(",")):
            name = f"{os.path.basename(path)}_{args.truths_key}_{filter_key}"
            if name not in record:
                record[name] = score("lorenz63", 3, observed, "amortised", update, filter_key, args.truths_key)
                print(name, record[name]["mse"], record[name]["diverged_steps"], flush=True)
                write_text_atomic(args.record, json.dumps(record, indent=1, default=float))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=("train", "score"))
    parser.add_argument("--observed", default="0,2", help="Lorenz-63's observed components (0-based)")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--key", type=int, default=300)
    parser.add_argument("--options", default="{}", help="JSON: training options on top of the experiment's")
    parser.add_argument("--out", default="/tmp/l63_trainings")
    parser.add_argument("--maps", default="")
    parser.add_argument("--filter-keys", default="0,1,2")
    parser.add_argument("--truths-key", type=int, default=TRUTHS_KEY)
    parser.add_argument("--record", default="trainings.json")
    args = parser.parse_args()
    observed = tuple(int(i) for i in args.observed.split(","))
    train(args, observed) if args.action == "train" else score_maps(args, observed)


if __name__ == "__main__":
    main()
