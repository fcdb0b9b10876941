"""OT at scale: the static and dynamic examples over the state dimension, against EXACT posteriors.

    PYTHONPATH=. python benchmarks/ot_dimension.py [--dims 2,5,10,20,50] [--part static|dynamic|both]
        [--methods enkf,letkf,sir,ot,local_ot,local_etpf,letkf_etpf,local_ot_etpf,flow_matching,local_flow]
        (also ``ot_avgK`` / ``local_ot_avgK``: K trainings averaged, ``averaged_maps``)

A dynamic run merges its rows by n into the saved JSON (a later n added to earlier ones).

Every method on the same priors / truths: EnKF, LETKF (radius 0: told the coordinates are
independent), SIR, the global OT update, the localised one (radius 0) and the localised ETPF
(radius 0: each coordinate moved by the exact 1-D transport to its own importance weights, no
network) and its hybrids, the LETKF (``letkf_etpf``) or the localised OT update
(``local_ot_etpf``) on l^0.75, then the LETPF on l^0.25. Metrics
(``metrics.compare_to_product_grid``): W1 of each coordinate's marginal to the exact one,
averaged over coordinates and its worst coordinate, and the joint sliced W2 and energy distance
to N exact samples, each beside its Monte-Carlo floor (N exact samples scored the same way).

- static: lambda_w = 0.4, y = 1, N = 1000, one update per seed (``--seeds``), library defaults
  (since 0.2.6 the global update's width grows with n: 256 at n = 50, most of an hour an update
  on one CPU core; ``benchmarks/results/gpu/`` has that cell measured on a GPU).
- dynamic: N = 1000, 20 steps, ``--simulations``, time average over t >= 1; OT with the dynamic
  experiment's filter options (``experiments.dynamic_example.OT_FILTER_OPTIONS``) for both OT
  updates, changed by ``--ot-options`` (JSON, e.g. '{"prior_smoothing": 1.5}').

- cost: seconds of one update at the smallest and the largest n, global and localised.

Writes ot_dimension.{json,md,png} to --out (the JSON after each part).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # jaxlib's LAPACK threads fight XLA's on 2 cores

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

from ot_filter.experiments._common import methods_present, write_text_atomic  # noqa: E402
from ot_filter.experiments.dynamic_example import run_dynamic_example  # noqa: E402
from ot_filter.experiments.static_example import run_static_example  # noqa: E402

METHODS = ("enkf", "letkf", "sir", "ot", "local_ot", "local_etpf", "letkf_etpf", "local_ot_etpf")
LABELS = {"enkf": "EnKF", "letkf": "LETKF (r = 0)", "sir": "SIR", "ot": "OT (global)", "flow_matching": "flow matching (global)", "local_ot": "OT (localised)",
          "local_flow": "flow matching (localised)",
          "local_etpf": "LETPF (r = 0, exact 1-D transport)", "letkf_etpf": "LETKF + LETPF (l^0.25)",
          "local_ot_etpf": "OT (localised) + LETPF (l^0.25)"}
METRICS = ("w1", "w1_max", "sliced_w2", "energy")


def _label(name):
    """A method's column label; ``<method>_avgK`` (``averaged_maps``) is K trainings averaged."""
    base, _, count = name.rpartition("_avg")
    if base in LABELS and count.isdigit():
        return f"{LABELS[base]}, {count} trainings averaged"
    return LABELS.get(name, name)


def _methods(rows):
    """The methods the rows hold, in the experiments' order (``methods_present``)."""
    return methods_present({key for row in rows for key in row if key not in ("dim", "seconds", "floor")})


def static_rows(dims, seeds, methods=METHODS):
    rows = []
    for dim in dims:
        start = time.perf_counter()
        result = run_static_example(jax.random.key(2026), noise=0.4, num_particles=1000, num_seeds=seeds,
                                    dim=dim, methods=methods)
        summary = result["metrics"]
        row = {"dim": dim, "seconds": time.perf_counter() - start,
               "floor": {k: summary[f"floor_{k}"] for k in METRICS}}
        for name in methods:
            row[name] = {k: summary[name][k] for k in METRICS}
            row[name]["modes_held"] = summary[name]["seeds_holding_both_modes"]
            if "diverged_seeds" in summary[name]:
                row[name]["diverged"] = summary[name]["diverged_seeds"]
        rows.append(row)
        print(f"static n={dim}: " + ", ".join(f"{n} {row[n]['w1']['mean']:.3f}" for n in methods)
              + f"; floor {row['floor']['w1']['mean']:.3f}; {row['seconds']:.0f} s", flush=True)
    return rows


def dynamic_rows(dims, simulations, steps, save=None, methods=METHODS, ot_options=None):
    rows = []
    for dim in dims:
        start = time.perf_counter()
        result = run_dynamic_example(jax.random.key(2026), dim=dim, num_particles=1000, num_steps=steps,
                                     num_simulations=simulations, methods=methods, bandwidth=4.0,
                                     standardise=True, average_from=1.0, keep=0, ot_options=ot_options)
        summary = result["metrics"]
        row = {"dim": dim, "seconds": time.perf_counter() - start, "floor": summary["floor"]}
        for name in methods:
            row[name] = dict(summary[name]["exact"], published_mmd=summary[name]["mmd_average"],
                             seconds_per_step=summary[name]["seconds_per_step"],
                             diverged_steps=summary[name].get("diverged_steps", 0))
        rows.append(row)
        print(f"dynamic n={dim}: " + ", ".join(f"{n} {row[n]['w1']['mean']:.3f}" for n in methods)
              + f"; floor {row['floor']['w1']['mean']:.3f}; {row['seconds']:.0f} s", flush=True)
        if save is not None:
            save(rows)  # each n as it finishes: a long sweep cut short keeps what it measured
    return rows


def seconds_of_update(update, dim, repeats=3):
    """(best seconds of one jitted update after compilation, compile seconds): the static example,
    N = 1000 prior particles, y = 1."""
    import jax.numpy as jnp

    from ot_filter.models import squared_observation

    model = squared_observation(dim=dim, noise=0.4, observation_scale=0.5, static=True)
    prior = jax.vmap(model.sample_initial)(jax.random.split(jax.random.key(0), 1000))
    state = update.init(jax.random.key(1), prior, model)
    apply = jax.jit(lambda key, state: update.apply(key, state, prior, jnp.ones(dim), model)[0])
    start = time.perf_counter()
    apply(jax.random.key(2), state).block_until_ready()
    first = time.perf_counter() - start
    times = []
    for repeat in range(repeats):
        start = time.perf_counter()
        apply(jax.random.key(3 + repeat), state).block_until_ready()
        times.append(time.perf_counter() - start)
    return min(times), max(first - min(times), 0.0)


def cost_rows(dims, repeats=3):
    """Seconds of one update (static example, N = 1000, defaults) after compilation, best of
    ``repeats``, global and localised, every n in one run (ratios are what carry over)."""
    import ot_filter as otf
    from ot_filter.models import squared_observation

    rows = []
    for dim in dims:
        geometry = squared_observation(dim=dim, static=True).geometry
        row = {"dim": dim}
        for name, update in (("ot", otf.ot()), ("local_ot", otf.local_ot(otf.local_windows(geometry, 0.0)))):
            seconds, compile_s = seconds_of_update(update, dim, repeats)
            row[name] = {"seconds": seconds, "compile_s": compile_s}
        rows.append(row)
        print(f"cost n={dim}: global {row['ot']['seconds']:.2f} s, localised {row['local_ot']['seconds']:.2f} s",
              flush=True)
    for row in rows:
        for name in ("ot", "local_ot"):
            row[name]["ratio_to_first"] = row[name]["seconds"] / rows[0][name]["seconds"]
    return rows


def _cell(entry):
    return "–" if entry is None else f"{entry['mean']:.3f} ± {entry['stderr']:.3f}"


def _entry(row, name, metric):
    return row[name][metric] if name in row else None  # a method the run left out


def _table(title, rows, extra=None):
    lines = [f"## {title}", ""]
    for metric, label in (("w1", "W1 per coordinate (mean over coordinates)"),
                          ("w1_max", "W1 of the worst coordinate"),
                          ("sliced_w2", "sliced W2 (joint)"), ("energy", "energy distance (joint)")):
        lines += [f"### {label}", "", "| n | " + " | ".join(_label(n) for n in _methods(rows)) + " | floor (N exact) |",
                  "|--:|" + "--:|" * (len(_methods(rows)) + 1)]
        for row in rows:
            lines.append(f"| {row['dim']} | " + " | ".join(_cell(_entry(row, n, metric)) for n in _methods(rows))
                         + f" | {_cell(row['floor'][metric])} |")
        lines.append("")
    if extra:
        lines += extra(rows)
    return lines


def _dynamic_extra(rows):
    """The published metric, and each trained method's seconds a step and fallen-back steps."""
    methods = _methods(rows)
    trained = [n for n in methods if n in ("ot", "flow_matching", "local_flow") or "local_ot" in n or n.startswith(("ot_", "flow_matching_"))]

    def per_method(row, field, fmt):
        return ", ".join(fmt(row[n][field]) if n in row and field in row[n] else "–" for n in trained)

    lines = ["### The published metric (standardised MMD, bandwidth 4) and cost", "",
             "| n | " + " | ".join(_label(n) for n in methods)
             + f" | s/step ({', '.join(trained)}) | diverged steps ({', '.join(trained)}) |",
             "|--:|" + "--:|" * (len(methods) + 2)]
    for row in rows:
        lines.append(f"| {row['dim']} | " + " | ".join(_cell(_entry(row, n, "published_mmd")) for n in methods)
                     + f" | {per_method(row, 'seconds_per_step', lambda v: f'{v:.3f}')}"
                     + f" | {per_method(row, 'diverged_steps', str)} |")
    return lines + [""]


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = [p for p in ("static", "dynamic") if results.get(p)]
    fig, axes = plt.subplots(1, len(parts), figsize=(6.2 * len(parts), 4.3), squeeze=False)
    for ax, part in zip(axes[0], parts):
        rows = results[part]
        dims = [r["dim"] for r in rows]
        for name in _methods(rows):
            have = [r for r in rows if name in r]
            ax.errorbar([r["dim"] for r in have], [r[name]["w1"]["mean"] for r in have],
                        [2 * r[name]["w1"]["stderr"] for r in have], marker="o", capsize=3, label=_label(name))
        # markers too: a sweep with one n still shows its floor
        ax.plot(dims, [r["floor"]["w1"]["mean"] for r in rows], "k--", marker="_", markersize=14,
                label="N exact samples (floor)")
        ax.plot(dims, [2 * r["floor"]["w1"]["mean"] for r in rows], "k:", marker="_", markersize=14,
                label="twice the floor")
        ax.set(xscale="log", yscale="log", xlabel="state dimension n",
               ylabel="W1 to the exact marginals (mean over coordinates)",
               title=("Static example, one update (N = 1000)" if part == "static"
                      else "Dynamic example, filter (N = 1000, t ≥ 1)"))
        ax.set_xticks(dims, [str(d) for d in dims])
        ax.set_xticks([], minor=True)  # no log-scale minor labels over the chosen ticks
        ax.grid(alpha=0.3, which="both")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def write_report(results, out):
    """ot_dimension.md and ot_dimension.png from the results (also of a sweep cut short)."""
    lines = ["# OT at scale: accuracy against the exact posterior over the state dimension", "",
             "Generated by `benchmarks/ot_dimension.py`; mean ± s.e. over seeds (static) or simulations "
             "(dynamic). The floor is N = 1000 exact samples scored the same way.", ""]
    if results.get("cost"):
        lines += ["## Cost of one update (static example, N = 1000, defaults; best of 3 after compilation, one run)", "",
                  "| n | global OT (s) | ratio to the first n | localised OT (s) | ratio to the first n |",
                  "|--:|--:|--:|--:|--:|"]
        for row in results["cost"]:
            lines.append(f"| {row['dim']} | {row['ot']['seconds']:.2f} | {row['ot']['ratio_to_first']:.2f} | "
                         f"{row['local_ot']['seconds']:.2f} | {row['local_ot']['ratio_to_first']:.2f} |")
        lines.append("")
        if results.get("cost_note"):  # what changed since the costs were measured
            lines += [results["cost_note"], ""]
    if results.get("static"):
        lines += _table(f"Static example (lambda_w = 0.4, y = 1, N = 1000, {results['static_seeds']} seeds, "
                        "library defaults)", results["static"])
    if results.get("dynamic"):
        lines += _table(f"Dynamic example (N = 1000, {results['dynamic_simulations']} simulations, "
                        "time average over t ≥ 1)", results["dynamic"], _dynamic_extra)
    write_text_atomic(os.path.join(out, "ot_dimension.md"), "\n".join(lines) + "\n")
    plot(results, os.path.join(out, "ot_dimension.png"))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dims", default="2,5,10,20,50")
    parser.add_argument("--part", choices=("static", "dynamic", "cost", "both", "all"), default="all")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--simulations", type=int, default=10)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--ot-options", default="{}",
                        help="dynamic part: overrides of the experiment's OT filter options, as JSON")
    args = parser.parse_args()
    # JSON has no tuples: a list is a (first, floor) schedule or another pair.
    ot_options = {k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(args.ot_options).items()}
    methods = tuple(args.methods.split(","))
    dims = [int(v) for v in args.dims.split(",")]
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "ot_dimension.json")
    results = json.load(open(path)) if os.path.exists(path) else {}
    results["device"] = str(jax.devices()[0])
    if args.part in ("cost", "all"):
        results["cost"] = cost_rows([dims[0], dims[-1]] if len(dims) > 1 else dims)
        write_text_atomic(path, json.dumps(results, indent=1))
    if args.part in ("static", "both", "all"):
        results["static"] = static_rows(dims, args.seeds, methods)
        results["static_seeds"] = args.seeds
        write_text_atomic(path, json.dumps(results, indent=1))
    if args.part in ("dynamic", "both", "all"):
        earlier = {row["dim"]: row for row in results.get("dynamic", [])
                   if results.get("dynamic_simulations") == args.simulations}

        results["dynamic_simulations"] = args.simulations

        def save(rows):
            merged = {**earlier, **{row["dim"]: row for row in rows}}
            results["dynamic"] = [merged[dim] for dim in sorted(merged)]
            write_text_atomic(path, json.dumps(results, indent=1))

        if ot_options:
            results["dynamic_ot_options"] = ot_options
        save(dynamic_rows(dims, args.simulations, args.steps, save, methods, ot_options))
    write_text_atomic(path, json.dumps(results, indent=1))
    write_report(results, args.out)


if __name__ == "__main__":
    main()
