"""A stored amortised map distilled into narrower networks: (a)'s accuracy and step cost against
the teacher's and the EnKF's (issue 18: (a) at most 3x the EnKF's step; at n = 2 and on
Lorenz-63 the width-64 map's forward pass kept it above).

    PYTHONPATH=.:benchmarks python benchmarks/amortised_distil.py --experiment dynamic --dim 2
        --map benchmarks/results/amortised_ot/maps/dynamic-n2 [--widths 16,24] [--iterations 20000]
        [--filter-keys 0] [--rounds 8] [--out DIR]
    PYTHONPATH=.:benchmarks python benchmarks/amortised_distil.py --experiment dynamic --dim 10
        --map benchmarks/results/amortised_ot/maps/dynamic-n10
        --teachers benchmarks/results/amortised_ot/maps/dynamic-n10/candidates/plain --widths 64 ...
    PYTHONPATH=.:benchmarks python benchmarks/amortised_distil.py --experiment lorenz63 --observed 0,2
        --map benchmarks/results/amortised_ot/maps/lorenz63-obs0,2 ...

1. The bank: the forecast ensembles of the teacher's own filter (a) on simulated trajectories of
   the offline stage's size (``offline_options``), a fifth held out.
2. ``distil_map`` for each width (of the average of --map and --teachers when given); the
   students are saved under ``DIR/maps``.
3. (a) with the teacher and with each student on the table's truths (``amortised_warm_from.score``:
   the dynamic example's W1 to the exact filter, Lorenz-63's MSE to the truth), every filter on the
   same filter keys (paired).
4. The step cost of the EnKF, the teacher's (a) and the students' (a), timed in turn in one
   process (``amortised_cost.measure``).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

from amortised_cost import measure  # noqa: E402
from amortised_warm_from import TRUTHS_KEY, score  # noqa: E402
from ot_filter.amortised import load_map, save_map  # noqa: E402
from ot_filter.amortised.distillation import distil_map  # noqa: E402
from ot_filter.experiments._common import write_text_atomic  # noqa: E402
from ot_filter.experiments.amortised import experiment_model, teacher_bank  # noqa: E402
from ot_filter.updates.amortised import amortised_ot  # noqa: E402
from ot_filter.updates.enkf import enkf  # noqa: E402

COST_STEPS = {"dynamic": 20, "lorenz63": 100}


def model_observed(args) -> tuple:
    return tuple(int(i) for i in args.observed.split(","))


def distil_all(args, model, teacher, record, path) -> dict:
    """The bank of the teacher's own forecasts and a student of each width (saved under --out/maps)."""
    bank_key, distil_key = jax.random.split(jax.random.key(args.key))
    started = time.perf_counter()
    training, validation = teacher_bank(bank_key, teacher, args.experiment, args.dim, model_observed(args))
    record["bank_s"] = time.perf_counter() - started
    maps = {"teacher": teacher}
    for width in (int(w) for w in args.widths.split(",")):
        teachers = [teacher] + [load_map(path) for path in filter(None, args.teachers.split(","))]
        student, history = distil_map(jax.random.fold_in(distil_key, width), teachers, model, training, validation,
                                      width=width, num_iterations=args.iterations,
                                      learning_rate=args.learning_rate)
        save_map(os.path.join(args.out, "maps", f"width{width}"), student)
        maps[f"width{width}"] = student
        record["students"][f"width{width}"] = {
            "seconds": history.seconds, "iterations": history.iterations.tolist(),
            "transport_error": history.transport_error.tolist(), "potential_error": history.potential_error.tolist()}
        print(f"width {width}: {history.seconds:.0f} s, held-out relative error of T "
              f"{history.transport_error[-1]:.4f}, of f {history.potential_error[-1]:.4f}", flush=True)
        write_text_atomic(path, json.dumps(record, indent=1, default=float))
    return maps


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiment", choices=("lorenz63", "dynamic"), required=True)
    parser.add_argument("--dim", type=int, default=2)
    parser.add_argument("--observed", default="0,2", help="Lorenz-63's observed components (0-based)")
    parser.add_argument("--map", required=True, help="the stored teacher map's directory")
    parser.add_argument("--teachers", default="",
                        help="further maps (comma-separated directories) whose average with --map the students fit")
    parser.add_argument("--widths", default="16,24")
    parser.add_argument("--iterations", type=int, default=20_000)
    parser.add_argument("--learning-rate", type=float, default=3e-3)
    parser.add_argument("--key", type=int, default=0, help="the bank's and the distillation's key")
    parser.add_argument("--filter-keys", default="0")
    parser.add_argument("--truths-key", type=int, default=TRUTHS_KEY)
    parser.add_argument("--rounds", type=int, default=8, help="timing rounds")
    parser.add_argument("--skip", default="", help="comma-separated parts to skip: score, cost")
    parser.add_argument("--reuse", action="store_true",
                        help="load the students saved under --out/maps instead of distilling (scores and costs only)")
    parser.add_argument("--out", default="/tmp/amortised_distil")
    args = parser.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    os.makedirs(os.path.join(args.out, "maps"), exist_ok=True)
    observed = model_observed(args)
    model = experiment_model(args.experiment, args.dim, observed)
    teacher = load_map(args.map)
    record = {"experiment": args.experiment, "dim": args.dim, "observed": list(observed), "map": args.map,
              "teacher_width": teacher.config.width, "teachers": args.teachers, "truths_key": args.truths_key, "students": {}, "scores": {}}
    path = os.path.join(args.out, "distil.json")

    if args.reuse:  # the students of an earlier run, and its record
        record = dict(json.load(open(path)), truths_key=args.truths_key)
        maps = {"teacher": teacher, **{f"width{w}": load_map(os.path.join(args.out, "maps", f"width{w}"))
                                       for w in (int(w) for w in args.widths.split(","))}}
    else:
        maps = distil_all(args, model, teacher, record, path)

    if "score" not in skip:
        for filter_key in (int(k) for k in args.filter_keys.split(",")):
            for label, one in maps.items():
                entry = score(args.experiment, args.dim, observed, "amortised", amortised_ot(one), filter_key,
                              args.truths_key)
                record["scores"][f"{label}_{filter_key}"] = entry
                print(label, filter_key, {k: v for k, v in entry.items() if not k.endswith("_per_simulation")}, flush=True)
                write_text_atomic(path, json.dumps(record, indent=1, default=float))

    if "cost" not in skip:
        updates = {"EnKF": enkf(), **{label: amortised_ot(one) for label, one in maps.items()}}
        seconds = measure(model, updates, COST_STEPS[args.experiment], 10, 1000, args.rounds)
        record["cost"] = {label: {"ms_per_step": value * 1e3, "vs_enkf": value / seconds["EnKF"]}
                          for label, value in seconds.items()}
        for label, value in record["cost"].items():
            print(f"{label}: {value['ms_per_step']:.3f} ms a step and simulation, {value['vs_enkf']:.2f}x the EnKF",
                  flush=True)
        write_text_atomic(path, json.dumps(record, indent=1, default=float))


if __name__ == "__main__":
    main()
