"""The checks issues 17 and 18 ask for on a GPU, one part per call, each result appended to one
JSON-lines file as soon as it is measured (a run cut short keeps what it measured).

    PYTHONPATH=. python benchmarks/gpu_checks.py --part iterations|static50|dynamic50|candidates
        [--out results.jsonl] [--sizes '[[n, width, batch], ...]'] [--variants '[[n, {...}], ...]']
        [--seeds S] [--ot-options '{...}'] [--smoke]
    PYTHONPATH=. python benchmarks/gpu_checks.py --part figure --records a.jsonl,b.jsonl --out width.png

- iterations: the OT update's cost at the sizes ``ot()`` picks (global n = 2, 10, 50, recorded in
  ``sizes``: the rule changes; localised
  n = 2, 50) and at the authors' width 384 with batches of 384 (global, n = 50): seconds of one
  update of ``k`` and ``2 k`` outer iterations after compilation (static example, N = 1000), so
  that the training loop's seconds per iteration (the difference) and the once-per-update work
  (simulating and transporting the N particles) separate; then one default update (10,000
  iterations) estimated from them.
- static50: the static example at n = 50 (lambda_w = 0.4, y = 1, N = 1000, 2 seeds), W1 per
  coordinate to the exact posterior: the global ``ot()`` with its defaults, with the authors'
  width 384 and batches of 384, and with width 384 and batches of 1024; the localised update.
  With ``--sizes``, the global update at each given [n, width, batch] instead (any n); with
  ``--variants``, at each [n, {ot() options}] (any of ``ot()``'s arguments); ``--seeds``: the
  number of seeds (2).
- dynamic50: the dynamic example at n = 50 (N = 1000, 10 simulations, 20 steps): EnKF, SIR, the
  global OT filter (never run at n = 50 on the CPU) and the localised one; with
  ``--ot-options``, the global filter alone with those options.
- candidates: the offline stage's candidate maps under ``--maps`` (training seconds, rounds,
  iterations), after ``benchmarks/amortised_ot.py`` trained them.
- figure: W1 against the width from the static records in ``--records`` (a PNG to ``--out``).

``--smoke`` shrinks every size (a check of the script, not a measurement).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import time

import jax

import ot_filter as otf
from ot_dimension import seconds_of_update  # benchmarks/ (the script's folder)
from ot_filter.models import squared_observation
from ot_filter.updates.ot import default_sizes

NUM_PARTICLES = 1000


def global_sizes(dim: int, options: dict) -> dict:
    """The width and batch the global update ran: ``options`` over ``ot()``'s rule for ``dim``
    (recorded: the rule changes)."""
    return dict(zip(("width", "batch_size"), default_sizes(dim)), **options)


def emit(out: str, record: dict) -> None:
    record = dict(record, device=str(jax.devices()[0]), jax=jax.__version__)
    line = json.dumps(record, default=float)
    print(line, flush=True)
    with open(out, "a") as handle:
        handle.write(line + "\n")


def iterations(out: str, smoke: bool) -> None:
    count = 20 if smoke else 400
    dims = (2, 5) if smoke else (2, 10, 50)
    cases = [(f"ot n={d}", d, lambda k, d=d, **o: otf.ot(num_iterations=k, **o), {}) for d in dims]
    cases += [(f"local_ot n={d}", d, lambda k, d=d, **o: otf.local_ot(
        otf.local_windows(squared_observation(dim=d, static=True).geometry, 0.0), num_iterations=k, **o), {})
        for d in (dims[0], dims[-1])]
    cases.append((f"ot n={dims[-1]} width 384 batch 384", dims[-1],
                  lambda k, **o: otf.ot(num_iterations=k, **o), {"width": 384, "batch_size": 384}))
    for label, dim, build, options in cases:
        one, compile_s = seconds_of_update(build(count, **options), dim, repeats=2)
        two, _ = seconds_of_update(build(2 * count, **options), dim, repeats=2)
        per_iteration = max(two - one, 1e-9) / count
        overhead = max(one - count * per_iteration, 0.0)
        # local_ot's sizes are its own (width 32, batch 128 then; 512 since 0.2.19), never the rule's
        used = global_sizes(dim, options) if label.startswith("ot") else None
        emit(out, {"part": "iterations", "case": label, "dim": dim, "options": options, "sizes": used,
                   "iterations_timed": [count, 2 * count], "seconds": [one, two],
                   "seconds_per_iteration": per_iteration, "iterations_per_s": 1 / per_iteration,
                   "per_update_overhead_s": overhead, "compile_s": compile_s,
                   "default_update_s_estimate": overhead + 10_000 * per_iteration})


def static50(out: str, smoke: bool, variants: list | None = None, seeds: int = 2) -> None:
    """``variants``: [[n, {ot() options}], ...] of the global update instead of the default ones."""
    from ot_filter.experiments.static_example import run_static_example
    dim = 5 if smoke else 50
    # The untried settings first: the authors' width and batch (an hour an update on one core here).
    defaults = [(dim, "ot width 384 batch 384", "ot", {"width": 384, "batch_size": 384}),
                (dim, "ot", "ot", {}), (dim, "local_ot", "local_ot", {}),
                (dim, "ot width 384 batch 1024", "ot", {"width": 384, "batch_size": 1024})]
    if variants:
        variants = [(n, " ".join(["ot"] + [f"{k} {v}" for k, v in options.items()]), "ot", options)
                    for n, options in variants]
    else:
        variants = defaults
    if smoke:
        variants = [(n if n < 10 else 5, label, method, dict(options, num_iterations=50))
                    for n, label, method, options in variants]
    for dim, label, method, options in variants:
        start = time.perf_counter()
        summary = run_static_example(jax.random.key(2026), noise=0.4, num_particles=NUM_PARTICLES, num_seeds=seeds,
                                     dim=dim, methods=(method,), ot_options=options or None)["metrics"]
        used = global_sizes(dim, options) if method == "ot" else None
        emit(out, {"part": "static", "case": label, "dim": dim, "seeds": seeds, "options": options, "sizes": used,
                   "w1": summary[method]["w1"]["mean"], "w1_stderr": summary[method]["w1"]["stderr"],
                   "w1_per_seed": summary[method]["w1_per_seed"], "w1_worst_coordinate": summary[method]["w1_max"]["mean"],
                   "floor_w1": summary["floor_w1"]["mean"], "floor_worst_coordinate": summary["floor_w1_max"]["mean"],
                   "seconds": time.perf_counter() - start})


def dynamic50(out: str, smoke: bool, ot_options: dict | None = None) -> None:
    """``ot_options``: the global OT filter's options (then it alone runs)."""
    from ot_filter.experiments.dynamic_example import OT_FILTER_OPTIONS, run_dynamic_example

    dim, simulations, steps = (5, 2, 12) if smoke else (50, 10, 20)
    runs = [("ot",), ("enkf", "sir", "local_ot")] if ot_options is None else [("ot",)]
    for methods in runs:  # the global filter was never run at n = 50
        start = time.perf_counter()
        summary = run_dynamic_example(jax.random.key(2026), dim=dim, num_particles=NUM_PARTICLES, num_steps=steps,
                                      num_simulations=simulations, methods=methods, bandwidth=4.0,
                                      standardise=True, average_from=1.0, keep=0, ot_options=ot_options)["metrics"]
        for name in methods:
            exact = summary[name]["exact"]
            # what the global filter ran: the experiment's options, ot()'s batch for n, the overrides
            used = dict(OT_FILTER_OPTIONS, batch_size=default_sizes(dim)[1], **(ot_options or {}))
            used = {k: v for k, v in used.items() if type(v) in (int, float, str, tuple)}  # not the optimisers
            emit(out, {"part": "dynamic", "case": name, "options": ot_options,
                       "sizes": used if name == "ot" else None, "dim": dim,
                       "simulations": simulations, "steps": steps,
                       "w1": exact["w1"]["mean"], "w1_stderr": exact["w1"]["stderr"],
                       "w1_worst_coordinate": exact["w1_max"]["mean"],
                       "floor_w1": summary["floor"]["w1"]["mean"],
                       "seconds_per_step": summary[name]["seconds_per_step"],
                       "diverged_steps": summary[name].get("diverged_steps", 0),
                       "seconds_of_the_run": time.perf_counter() - start})


def candidates(out: str, maps: str) -> None:
    for path in sorted(glob.glob(os.path.join(maps, "**", "map.json"), recursive=True)):
        with open(path) as handle:
            info = json.load(handle)["info"]
        emit(out, {"part": "offline", "map": os.path.relpath(os.path.dirname(path), maps),
                   **{k: info.get(k) for k in ("seconds", "rounds", "iterations", "simulations", "steps",
                                               "final_validation_loss", "averaged_chunks")},
                   "selection": info.get("selection")})


def figure(records: str, out: str) -> None:
    """W1 of the global update against its width (static example, batch 1024) from the records
    in the JSON-lines files ``records`` (comma-separated), one line per n, beside the floor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(line) for path in records.split(",") for line in open(path)]
    static = [r for r in rows if r["part"] == "static" and r["case"].startswith("ot")]
    with open("benchmarks/results/ot_dimension.json") as handle:
        cpu_rows = json.load(handle)["static"]
    with open("benchmarks/results/ot_dimension_size_rule/sizes.json") as handle:
        cpu_sizes = json.load(handle)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for dim in sorted({r["dim"] for r in static}):
        # "sizes": the width and batch used; records without it ran ot()'s rule of the time (width 64)
        points = sorted((r.get("sizes", {}).get("width") or r["options"].get("width", 64), r["w1"], r["w1_stderr"])
                        for r in static if r["dim"] == dim
                        and (r.get("sizes") or r["options"]).get("batch_size", 1024) == 1024)
        if not points:
            continue
        widths, w1, stderr = zip(*points)
        line = ax.errorbar(widths, w1, yerr=[2 * e for e in stderr], marker="o", capsize=3, label=f"n = {dim}, GPU")
        floor = next(r["floor_w1"] for r in static if r["dim"] == dim)
        ax.axhline(floor, color=line[0].get_color(), linestyle=":", linewidth=1)
        cpu = next((row["ot"]["w1"] for row in cpu_rows if row["dim"] == dim), None)
        # the CPU sweep's global OT at width 64, and the CPU's other widths on the same 2 seeds
        cpu_points = [(64, cpu["mean"], 2 * cpu["stderr"])] if cpu is not None else []
        cpu_points += [(r["options"]["width"], r["w1"], 0.0) for r in cpu_sizes
                       if r["dim"] == dim and r["seeds"] == 2 and r["options"].get("batch_size") == 1024
                       and "width" in r["options"]]
        if cpu_points:
            widths, w1, error = zip(*sorted(cpu_points))
            ax.errorbar(widths, w1, yerr=error, marker="s", mfc="none", capsize=3, color=line[0].get_color(),
                        linestyle="none", label=f"n = {dim}, on the CPU")
    ax.set(xscale="log", xlabel="network width (batch 1024)", ylabel="W1 to the exact marginals (mean over coordinates)",
           title="Global OT update, static example (N = 1000, 2 seeds, ±2 s.e.)\ndotted: floor of N exact samples")
    enkf = next(row["enkf"]["w1"]["mean"] for row in cpu_rows if row["dim"] == max(r["dim"] for r in static))
    ax.axhline(enkf, color="grey", linestyle="--", linewidth=1, label="EnKF at the largest n (CPU)")
    ax.set_xticks([64, 128, 256, 384], labels=["64", "128", "256", "384"])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    print(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("iterations", "static50", "dynamic50", "candidates", "figure"), required=True)
    parser.add_argument("--records", help="figure: the JSON-lines files to draw (comma-separated)")
    parser.add_argument("--out", default="gpu_checks.jsonl")
    parser.add_argument("--maps", default="benchmarks/results/amortised_ot/maps")
    parser.add_argument("--sizes", help='static50: the global update at [[n, width, batch], ...] (JSON)')
    parser.add_argument("--variants", help='static50: the global update at [[n, {ot() options}], ...] (JSON)')
    parser.add_argument("--seeds", type=int, default=2, help="static50: seeds (prior samples) per variant")
    parser.add_argument("--ot-options", help="dynamic50: the global OT filter's options (JSON)")
    parser.add_argument("--smoke", action="store_true")
    args = parser.parse_args()
    if args.part == "figure":
        figure(args.records, args.out)
    elif args.part == "candidates":
        candidates(args.out, args.maps)
    elif args.part == "static50":
        variants = json.loads(args.variants) if args.variants else None
        if args.sizes:
            variants = [[n, {"width": w, "batch_size": b}] for n, w, b in json.loads(args.sizes)]
        static50(args.out, args.smoke, variants, args.seeds)
    elif args.part == "dynamic50":
        options = json.loads(args.ot_options) if args.ot_options else None
        if options:  # JSON has no tuples: num_iterations=(first, floor)
            options = {k: tuple(v) if isinstance(v, list) else v for k, v in options.items()}
        dynamic50(args.out, args.smoke, options)
    else:
        iterations(args.out, args.smoke)


if __name__ == "__main__":
    main()
