"""Where amortised (b) should start when the offline map is an average of training iterates:
from the last iterate (the point the saddle-point game was at) or from the average (issue 18).

For one experiment setting: the offline stage as the runner runs it (``map_for``: the candidates,
trained at once in worker processes, the selection on held-out truths) with each round's map the
average of its 20 chunk ends (``average_chunks=20``), then on the table's truths
(``benchmarks/amortised_ot.py``'s key 2026, 10 simulations, N = 1000) over several filter keys,
each shared by every filter (paired): the online OT filter, (a), (b) from the last iterate and
(b) from the average.

    PYTHONPATH=. python benchmarks/amortised_warm_from.py --experiment lorenz63 --observed 0
        [--training-key 63] [--filter-keys 0,1,2] [--filters ot,amortised,...] [--maps DIR] [--out FILE.json]
        [--truths-key 2026]
    PYTHONPATH=. python benchmarks/amortised_warm_from.py --experiment dynamic --dim 2 ...

Lorenz-63: MSE of the mean to the truth after t = 1.5; the dynamic example: W1 to the exact
marginals (mean over coordinates). Records are written to ``--out`` as each is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

from ot_filter.experiments._common import write_text_atomic
from ot_filter.experiments.amortised import map_for, warm_options
from ot_filter.updates.amortised import amortised_ot

TRUTHS_KEY = 2026


def filters(trained, experiment: str) -> dict:
    options = {k: v for k, v in warm_options(trained, experiment).items() if k != "warm_from"}
    return {"amortised": amortised_ot(trained),
            "amortised_warm": amortised_ot(trained, **options),
            "amortised_warm_average": amortised_ot(trained, warm_from="average", **options)}


def score(experiment: str, dim: int, observed, name: str, update, filter_key: int, truths_key: int = TRUTHS_KEY) -> dict:
    """One filter on the truths of ``truths_key`` (default: the table's), every filter of one
    ``filter_key`` on the same keys."""
    # The truths depend on truths_key only; the filter's key on filter_key (it runs first: index 0).
    extra = {name: update} if update is not None else None
    methods = () if update is not None else ("ot",)
    if experiment == "lorenz63":
        from ot_filter.experiments import lorenz63

        summary = lorenz63.run_lorenz63(jax.random.key(truths_key), methods=methods, observed=observed, extra_updates=extra,
                                        filter_key=jax.random.key(filter_key))["metrics"]
        entry = summary[name]
        return {"mse": entry["mse_after_settle"]["mean"], "stderr": entry["mse_after_settle"]["stderr"],
                "mse_per_simulation": entry.get("mse_after_settle_per_simulation"),
                "diverged_steps": entry.get("diverged_steps"), "run_s": entry["run_s"]}
    from ot_filter.experiments import dynamic_example

    summary = dynamic_example.run_dynamic_example(jax.random.key(truths_key), dim=dim, num_particles=1000,
                                                  num_steps=20, num_simulations=10, methods=methods,
                                                  extra_updates=extra, filter_key=jax.random.key(filter_key))["metrics"]
    exact = summary[name]["exact"]
    return {"w1": exact["w1"]["mean"], "stderr": exact["w1"]["stderr"], "worst": exact["w1_max"]["mean"],
            "floor": summary["floor"]["w1"]["mean"], "diverged_steps": summary[name].get("diverged_steps"),
            "w1_per_simulation": exact.get("w1_per_simulation"),
            "run_s": summary[name]["run_s"]}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiment", choices=("lorenz63", "dynamic"), required=True)
    parser.add_argument("--dim", type=int, default=2)
    parser.add_argument("--observed", default="0,2", help="Lorenz-63's observed components (0-based)")
    parser.add_argument("--training-key", type=int, default=63)
    parser.add_argument("--filter-keys", default="0,1,2", help="the filter keys (comma-separated)")
    parser.add_argument("--filters", default="ot,amortised,amortised_warm,amortised_warm_average",
                        help="the filters to run (comma-separated)")
    parser.add_argument("--maps", default="/tmp/warm_from_maps")
    parser.add_argument("--out", default="warm_from.json")
    parser.add_argument("--truths-key", type=int, default=TRUTHS_KEY, help="the truths' key (default: the table's)")
    args = parser.parse_args()
    observed = tuple(int(i) for i in args.observed.split(","))
    where = os.path.join(args.maps, f"{args.experiment}-{args.dim}-{args.observed}-{args.training_key}")
    started = time.perf_counter()
    trained, _ = map_for(where, jax.random.key(args.training_key), args.experiment, dim=args.dim, observed=observed,
                         average_chunks=20)
    record = {"experiment": args.experiment, "dim": args.dim, "observed": list(observed), "truths_key": args.truths_key,
              "training_key": args.training_key, "stage_s": time.perf_counter() - started,
              "selection": trained.info.get("selection"), "filters": {}}
    chosen = args.filters.split(",")
    for filter_key in (int(k) for k in args.filter_keys.split(",")):
        for name, update in [("ot", None), *filters(trained, args.experiment).items()]:
            if name not in chosen:
                continue
            record["filters"][f"{name}_{filter_key}"] = score(args.experiment, args.dim, observed, name, update,
                                                              filter_key, args.truths_key)
            print(name, filter_key, record["filters"][f"{name}_{filter_key}"], flush=True)
            write_text_atomic(args.out, json.dumps(record, indent=1, default=float))


if __name__ == "__main__":
    main()
