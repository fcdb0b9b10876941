"""Amortised OT filtering (issue 18): offline-trained maps against the online OT filter, the EnKF
and SIR on the chapter's dynamic example (n = 2, 10; W1 to the exact marginals) and Lorenz-63
(components 1 and 3 observed, the chapter's setting, and x1 only; MSE of the mean).

    PYTHONPATH=. python benchmarks/amortised_ot.py [--part dynamic|lorenz63|all] [--dims 2,10]
        [--observed "0,2;0"] [--simulations 10] [--out benchmarks/results/amortised_ot]

Each map's candidates are trained once into OUT/maps/NAME/candidates, the one kept (by its filter's
MSE to held-out simulated truths) into OUT/maps/NAME (``experiments.amortised.map_for``), and reused by
a rerun. Every method of one experiment runs in one process on the same truths, so the per-step
costs are ratios measured in one run. Writes OUT/amortised_ot.{json,md} and the figures.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

from ot_filter.experiments._common import write_text_atomic  # noqa: E402
from ot_filter.experiments.amortised import (  # noqa: E402
    WARM_OPTIONS, map_for, map_name, plot_validation, run_amortised_dynamic, run_amortised_lorenz63,
    warm_map_for, warm_options,
)

METHODS = ("enkf", "sir", "ot", "amortised", "amortised_warm")
LABELS = {"enkf": "EnKF", "sir": "SIR", "ot": "OT, online", "amortised": "amortised (a): no training",
          "amortised_warm": "amortised (b): warm-started, a few iterations a step"}


def _row(summary, name, metric):
    entry = summary[name]
    value = entry["exact"]["w1"] if metric == "w1" else entry["mse_after_settle"]
    return {"error": value["mean"], "stderr": value["stderr"], "run_s": entry["run_s"],
            "compile_s": entry["compile_s"], "diverged_steps": entry.get("diverged_steps", 0),
            "per_simulation": entry["exact"]["w1_per_simulation"] if metric == "w1" else None,
            # the worst coordinate's time-averaged W1 (sees one coordinate's lost mode)
            "worst_coordinate": entry["exact"]["w1_max"]["mean"] if metric == "w1" else None,
            "worst_coordinate_stderr": entry["exact"]["w1_max"]["stderr"] if metric == "w1" else None}


def _finish(rows, num_steps, num_simulations, trained, training_s):
    steps = num_steps * num_simulations
    for row in rows.values():
        row["seconds_per_step"] = row["run_s"] / steps
    enkf, online = rows["enkf"]["seconds_per_step"], rows["ot"]["seconds_per_step"]
    for row in rows.values():
        row["cost_vs_enkf"] = row["seconds_per_step"] / enkf
    # (b) pays the offline stage once (every candidate's training and the selection) and saves
    # (online - b) per step and simulation.
    saving = online - rows["amortised_warm"]["seconds_per_step"]
    offline = trained.info["selection"]["offline_seconds"] if "selection" in trained.info else trained.info["seconds"]
    return {"methods": rows, "offline_training_s": offline, "offline_info": trained.info,
            "training_wall_s": training_s,
            "break_even_steps_b": offline / saving if saving > 0 else None,
            "break_even_steps_a": offline / (online - rows["amortised"]["seconds_per_step"]),
            "a_vs_online": rows["amortised"]["error"] / rows["ot"]["error"],
            "b_vs_online": rows["amortised_warm"]["error"] / rows["ot"]["error"]}


def _compare(experiment, key, simulations, out, run, metric, **model):
    """Trains (or loads) the experiment's map, runs every method on the same truths."""
    name = map_name(experiment, **model)
    started = time.perf_counter()
    directory = os.path.join(out, "maps", name)
    trained, _ = map_for(directory, key, experiment, **model)
    training_s = time.perf_counter() - started
    warm = warm_map_for(directory, trained)  # (b)'s start (Lorenz-63: selected on its own)
    summary = run(jax.random.key(2026), trained, num_simulations=simulations, warm=warm, **model)["metrics"]
    rows = {m: _row(summary, m, metric) for m in METHODS}
    record = _finish(rows, summary["num_steps"], simulations, trained, training_s)
    record["warm_options"] = warm_options(warm, experiment)
    if metric == "w1":
        record.update(experiment=f"dynamic n = {model['dim']}",
                      metric="W1 to the exact marginals (mean over coordinates, t >= 1)",
                      floor=summary["floor"]["w1"]["mean"], floor_stderr=summary["floor"]["w1"]["stderr"],
                      floor_worst_coordinate=summary["floor"]["w1_max"]["mean"])
    else:
        record.update(experiment=f"Lorenz-63, observed {','.join(str(i + 1) for i in model['observed'])}",
                      metric="MSE of the mean after t = 1.5 (to the truth)")
    print(json.dumps({k: v for k, v in record.items() if k != "methods"}, default=float))
    for m, row in rows.items():
        print(f"  {m}: {row['error']:.4f} ± {row['stderr']:.4f}, {row['seconds_per_step'] * 1e3:.3f} ms/step, "
              f"{row['cost_vs_enkf']:.1f}x EnKF, diverged {row['diverged_steps']}", flush=True)
    return record


def markdown(records):
    lines = ["# Amortised OT filtering: offline maps against the online OT filter", "",
             "Generated by `benchmarks/amortised_ot.py` (10 simulations each, N = 1000, one process per part: the "
             "costs of one table are measured in one run). Error: mean ± s.e. over simulations. Cost: run seconds "
             "per step and simulation (compile excluded), and as a ratio to the EnKF's.", ""]
    for record in records:
        lines += [f"## {record['experiment']}", "", f"Metric: {record['metric']}."
                  + (f" Floor (N exact samples): {record['floor']:.4f} ± {record['floor_stderr']:.4f}."
                     if "floor" in record else ""), "",
                  "| method | error | worst coordinate | ms per step | cost / EnKF | diverged steps |",
                  "|--|--:|--:|--:|--:|--:|"]
        for m, row in record["methods"].items():
            worst = (f"{row['worst_coordinate']:.4f} ± {row['worst_coordinate_stderr']:.4f}"
                     if row.get("worst_coordinate") is not None else "–")
            lines.append(f"| {LABELS[m]} | {row['error']:.4f} ± {row['stderr']:.4f} | {worst} | "
                         f"{row['seconds_per_step'] * 1e3:.3f} | {row['cost_vs_enkf']:.1f} | {row['diverged_steps']} |")
        if record.get("floor_worst_coordinate") is not None:
            lines.append(f"| floor (N exact samples) | {record['floor']:.4f} | {record['floor_worst_coordinate']:.4f} | | | |")
        info = record["offline_info"]
        warm = record.get("warm_options") or WARM_OPTIONS["dynamic" if record["experiment"].startswith("dynamic")
                                                          else "lorenz63"]
        lines += ["", f"- (b): `amortised_ot(map, {', '.join(f'{k}={v}' for k, v in warm.items())})`.",
                  f"- (a) / online OT error: {record['a_vs_online']:.2f}; (b) / online OT: {record['b_vs_online']:.2f}.",
                  f"- Offline training of the map kept: {info['seconds']:.0f} s ({info['rounds']} rounds, "
                  f"{info['iterations']} iterations, {info['simulations']} simulations of {info['steps']} steps).",
                  *_selection_lines(info),
                  "- Break-even against the online OT filter: (b) after "
                  + (f"{record['break_even_steps_b']:.0f}" if record["break_even_steps_b"] else "never")
                  + f" filtered steps (simulations x steps), (a) after {record['break_even_steps_a']:.0f}.", ""]
    return "\n".join(lines) + "\n"


def _selection_lines(info):
    """The candidates' scores on the held-out truths and the whole offline stage's cost."""
    if "selection" not in info:
        return []
    selection = info["selection"]
    scores = "; ".join(f"{label} {score['mse']:.3f} ± {score['stderr']:.3f} ({score['fallback_steps']} fallbacks)"
                       for label, score in selection["scores"].items())
    lines = [f"- Candidates, (a)'s MSE to held-out simulated truths: {scores}; kept: {selection['chosen']}. "
             f"The offline stage (every candidate and the selection): {selection['offline_seconds']:.0f} s."]
    if "warm" in selection:  # (b)'s start selected on its own (WARM_SELECTED)
        warm = "; ".join(f"{label} {score['mse']:.3f} ± {score['stderr']:.3f} ({score['fallback_steps']} fallbacks)"
                         for label, score in selection["warm"]["scores"].items())
        lines.append(f"- (b)'s MSE on the same truths: {warm}; (b) starts from: {selection['warm']['chosen']}.")
    return lines


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--part", choices=("dynamic", "lorenz63", "all"), default="all")
    parser.add_argument("--dims", default="2,10")
    parser.add_argument("--observed", default="0,2;0")
    parser.add_argument("--simulations", type=int, default=10)
    parser.add_argument("--out", default="benchmarks/results/amortised_ot")
    parser.add_argument("--merge", help="another run's amortised_ot.json whose experiments join OUT's (then "
                                        "the tables and figure are rewritten; nothing runs)")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "amortised_ot.json")
    records = json.load(open(path)) if os.path.exists(path) else []
    new = []
    if args.merge:
        new = json.load(open(args.merge))
    elif args.part in ("dynamic", "all"):
        new += [_compare("dynamic", jax.random.key(18), args.simulations, args.out, run_amortised_dynamic, "w1",
                         dim=int(d)) for d in args.dims.split(",")]
    if args.part in ("lorenz63", "all") and not args.merge:
        new += [_compare("lorenz63", jax.random.key(63), args.simulations, args.out, run_amortised_lorenz63, "mse",
                         observed=tuple(int(i) for i in group.split(","))) for group in args.observed.split(";")]
    names = {r["experiment"] for r in new}
    records = [r for r in records if r["experiment"] not in names] + new
    write_text_atomic(path, json.dumps(records, indent=1, default=float))
    write_text_atomic(os.path.join(args.out, "amortised_ot.md"), markdown(records))
    stored = {}
    for name in sorted(os.listdir(os.path.join(args.out, "maps"))):
        history = os.path.join(args.out, "maps", name, "history.npz")
        record = os.path.join(args.out, "maps", name, "map.json")
        if os.path.exists(history) and os.path.exists(record):
            with open(record) as handle:
                chosen = json.load(handle)["info"].get("selection", {})
            stored[f"{name} (kept: {chosen['chosen']})" if chosen else name] = dict(np.load(history))
    if stored:
        plot_validation(stored, args.out)


if __name__ == "__main__":
    main()
