"""``run_experiment``: resolve options, run the missing cells, summarise, draw the figures.

A cell's numbers are stored as soon as it finishes (``store.RunDirectory``); rerunning the same
command on the same output directory skips the finished cells, and the summary is rebuilt from
the stored cells in a fixed order, so ``metrics.json`` after an interrupted-then-resumed run is
byte-identical to an uninterrupted one. Timings (compile and run seconds, separately) go to
``timings.json``, never into ``metrics.json``.
"""

from __future__ import annotations

import itertools
import json
import os
import platform
import sys
import time
from typing import Callable, NamedTuple

import numpy as np

from ot_filter.runner.catalogue import EXPERIMENTS, blocks
from ot_filter.runner.store import RunDirectory, RunError

__all__ = ["RunInterrupted", "RunOutput", "resolve_options", "run_experiment"]


class RunInterrupted(Exception):
    """The run stopped between cells on request (e.g. Ctrl-C); rerunning resumes it."""

SINGLE_VALUED = ("seed", "steps", "simulations", "block", "dt")
POSITIVE_INTS = ("particles", "dim", "steps", "simulations", "block", "map_iterations")


class RunOutput(NamedTuple):
    out: str
    metrics: dict
    figures: list
    cells_run: int
    cells_skipped: int


def resolve_options(name: str, overrides: dict | None = None, quick: bool = False) -> dict:
    """The experiment's defaults, then its ``--quick`` settings, then ``overrides``; validated.
    Raises ``RunError`` (one line) on an unknown experiment, option or value."""
    if name not in EXPERIMENTS:
        raise RunError(f"unknown experiment {name!r}; available: {', '.join(EXPERIMENTS)}")
    experiment = EXPERIMENTS[name]
    options = dict(experiment.defaults)
    if quick:
        options.update(experiment.quick)
    for key, value in (overrides or {}).items():
        if value is None:
            continue
        if key not in experiment.defaults:
            raise RunError(
                f"--{key.replace('_', '-')} does not apply to {name}; its options: "
                f"{', '.join('--' + k.replace('_', '-') for k in experiment.defaults)}"
            )
        options[key] = value
    for key in ("particles", "dim", "noise", "methods"):
        if key in options:
            value = options[key]
            options[key] = tuple(value) if isinstance(value, (list, tuple)) else (value,)
    for key in POSITIVE_INTS:
        if key in options:
            values = options[key] if isinstance(options[key], tuple) else (options[key],)
            for value in values:
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                    raise RunError(f"--{key.replace('_', '-')} must be a positive integer, got {value!r}")
    if "steps" in options and options["steps"] < experiment.minimum_steps:
        raise RunError(f"--steps must be >= {experiment.minimum_steps} for {name}, got {options['steps']}")
    if "particles" in options and min(options["particles"]) < 2:
        raise RunError(f"--particles must be >= 2, got {min(options['particles'])}")
    if isinstance(options.get("seed"), bool) or not isinstance(options.get("seed"), (int, np.integer)) or options["seed"] < 0:
        raise RunError(f"--seed must be an integer >= 0, got {options.get('seed')!r}")
    if "noise" in options and not all(isinstance(v, (int, float)) and v > 0 for v in options["noise"]):
        raise RunError(f"--noise values must be > 0, got {options['noise']}")
    gate = options.get("map_gate")
    if gate is not None and (isinstance(gate, bool) or not isinstance(gate, (int, float)) or not 0 <= gate < np.inf):
        raise RunError(f"--map-gate must be a finite ratio > 0, or 0 for none, got {gate!r}")
    if options.get("maps") is not None and not isinstance(options["maps"], str):
        raise RunError(f"--maps must be a directory, got {options['maps']!r}")
    if "dt" in options and not (isinstance(options["dt"], (int, float)) and options["dt"] > 0):
        raise RunError(f"--dt must be > 0, got {options['dt']!r}")
    for key in ("particles", "dim", "noise"):
        if key in options and len(options[key]) > 1 and key not in experiment.sweep:
            raise RunError(f"--{key} takes one value for {name} (sweeps: {', '.join(experiment.sweep) or 'none'})")
        if key in options and len(set(options[key])) != len(options[key]):
            raise RunError(f"--{key} lists a value twice: {options[key]}")
    unknown = [m for m in options["methods"] if m not in experiment.methods]
    if unknown or not options["methods"]:
        raise RunError(f"unknown method(s) {', '.join(unknown) or '(none given)'} for {name}; "
                       f"available: {', '.join(experiment.methods)}")
    options["experiment"] = name
    return options


def cells_of(options: dict) -> list[dict]:
    """Every cell: method x swept values x simulation block, in a fixed order."""
    axes = [(k, options[k]) for k in ("dim", "noise", "particles") if k in options]
    cells = []
    for method in options["methods"]:
        for values in itertools.product(*(v for _, v in axes)):
            for block, size in enumerate(blocks(options["simulations"], options["block"])):
                cell = {"method": method, **dict(zip((k for k, _ in axes), values)),
                        "block": block, "simulations": size}
                cells.append(cell)
    return cells


def cell_id(cell: dict) -> str:
    return "_".join(f"{k}-{cell[k]}" for k in ("method", "dim", "noise", "particles", "block") if k in cell)


def _config(options: dict, quick: bool, command: list | None) -> dict:
    import jax

    import ot_filter

    return {
        "experiment": options["experiment"],
        "options": {k: list(v) if isinstance(v, tuple) else v for k, v in options.items()},
        "quick": quick,
        "command": command if command is not None else ["ot-filter", *sys.argv[1:]],
        "ot_filter_version": ot_filter.__version__,
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "x64": bool(jax.config.jax_enable_x64),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
    }


def _summarise(options: dict, records: list) -> tuple[dict, list]:
    """Groups the cells (method x swept values) in the cells' order; per group the per-simulation
    numbers concatenated over blocks with their mean / s.e., counts summed, curves averaged."""
    groups: dict = {}
    for cell, record, arrays in records:
        key = tuple((k, cell[k]) for k in ("method", "dim", "noise", "particles") if k in cell)
        group = groups.setdefault(key, {**dict(key), "per_simulation": {}, "counts": {}, "curves": {},
                                        "arrays": None})
        for name, values in record["per_simulation"].items():
            group["per_simulation"].setdefault(name, []).extend(values)
        for name, value in record["counts"].items():
            group["counts"][name] = group["counts"].get(name, 0) + value
        for name in record["curves"]:
            group["curves"].setdefault(name, []).append(arrays["curve_" + name])
        if group["arrays"] is None:
            group["arrays"] = {k[len("figure_"):]: v for k, v in arrays.items() if k.startswith("figure_")}
    summary = []
    for group in groups.values():
        per_sim = {}
        for name, values in group["per_simulation"].items():
            values = np.asarray(values, float)
            se = float(values.std(ddof=1) / np.sqrt(values.size)) if values.size > 1 else 0.0
            per_sim[name] = {"mean": float(values.mean()), "se": se, "values": values.tolist()}
        curves = {}
        for name, parts in group["curves"].items():
            stacked = np.concatenate(parts)  # [S, T]
            se = stacked.std(axis=0, ddof=1) / np.sqrt(len(stacked)) if len(stacked) > 1 else 0 * stacked[0]
            curves[name] = {"mean": stacked.mean(axis=0).tolist(), "se": np.asarray(se).tolist()}
        summary.append({**{k: v for k, v in group.items() if k not in ("per_simulation", "curves")},
                        "per_simulation": per_sim, "curves": curves})
    metrics = {
        "experiment": options["experiment"],
        "options": {k: list(v) if isinstance(v, tuple) else v for k, v in options.items()},
        "results": [{k: v for k, v in g.items() if k != "arrays"} for g in summary],
    }
    return metrics, summary


def run_experiment(
    name: str,
    overrides: dict | None = None,
    out: str | None = None,
    quick: bool = False,
    progress: bool = True,
    command: list | None = None,
    log: Callable[[str], None] = print,
    stop_requested: Callable[[], bool] = lambda: False,
) -> RunOutput:
    """Runs (or resumes) experiment ``name`` into ``out``; returns the summary and figure paths.

    ``overrides``: option -> value (``particles``, ``dim``, ``steps``, ``simulations``, ``seed``,
    ``methods``, ``block``, ...; only the experiment's own). ``progress``: a progress bar over
    cells and, inside the compiled filters, step reports (about 20 per run). ``stop_requested``
    is polled between cells: when it returns True the run stops with ``RunInterrupted`` (the
    finished cells stay stored).
    """
    from ot_filter.progress import every_fraction, progress_listener

    options = resolve_options(name, overrides, quick)
    out = out or os.path.join("ot-filter-runs", name + ("-quick" if quick else ""))
    experiment = EXPERIMENTS[name]
    run = RunDirectory.open(out, _config(options, quick, command), ("experiment", "options", "ot_filter_version"))
    cells = cells_of(options)
    pending = [c for c in cells if not run.is_finished(cell_id(c))]
    if len(pending) < len(cells):
        log(f"resuming {out}: {len(cells) - len(pending)} of {len(cells)} cells already finished")
    step_every = every_fraction(options.get("steps", 1)) if progress else 0
    bar = _progress_bar(len(cells), len(cells) - len(pending), name, enabled=progress)
    try:
        for cell in pending:
            if stop_requested():
                raise RunInterrupted(f"stopped before cell {cell_id(cell)}")
            bar.set_postfix_str(cell_id(cell))
            started = time.perf_counter()
            with progress_listener(lambda done, total: bar.set_postfix_str(f"{cell_id(cell)} step {done}/{total}")):
                # The run directory rides along (not in the stored options): cells that train
                # something once per run (an amortised OT map) keep it there for later cells and runs.
                result = experiment.run_cell(dict(options, run_dir=out), cell, step_every)
            record = {
                "cell": cell,
                "per_simulation": {k: [float(x) for x in v] for k, v in result.per_simulation.items()},
                "counts": {k: int(v) for k, v in result.counts.items()},
                "curves": sorted(result.curves),
                "timing": {**{k: float(v) for k, v in result.timing.items()},
                           "wall_s": time.perf_counter() - started},
            }
            arrays = {**{"curve_" + k: np.asarray(v) for k, v in result.curves.items()},
                      **{"figure_" + k: np.asarray(v) for k, v in result.arrays.items()}}
            run.save_cell(cell_id(cell), record, arrays)
            bar.update(1)
    finally:
        bar.close()
    records = []
    for cell in cells:
        record, arrays = run.load_cell(cell_id(cell))
        records.append((cell, record, arrays))
    metrics, groups = _summarise(options, records)
    run.write_json("metrics.json", metrics)
    timings = {cell_id(c): r["timing"] for c, r, _ in records}
    run.write_json("timings.json", {
        "cells": timings,
        "total_compile_s": sum(t.get("compile_s", 0.0) for t in timings.values()),
        "total_run_s": sum(t.get("run_s", 0.0) for t in timings.values()),
    })
    figures = experiment.plot(options, groups, out)
    _write_summary_arrays(run, groups)
    log(_table(metrics))
    return RunOutput(out, metrics, figures, len(pending), len(cells) - len(pending))


def _write_summary_arrays(run: RunDirectory, groups: list) -> None:
    """``arrays.npz``: each group's mean curves and per-simulation numbers (raw arrays)."""
    import io

    from ot_filter.runner.store import write_bytes_atomic

    arrays = {}
    for g in groups:
        tag = cell_id({**g, "block": "all"}).replace("_block-all", "")
        for name, curve in g["curves"].items():
            arrays[f"{tag}/{name}_mean"] = np.asarray(curve["mean"])
            arrays[f"{tag}/{name}_se"] = np.asarray(curve["se"])
        for name, values in g["per_simulation"].items():
            arrays[f"{tag}/{name}"] = np.asarray(values["values"])
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_bytes_atomic(os.path.join(run.root, "arrays.npz"), buffer.getvalue())


def _table(metrics: dict) -> str:
    lines = []
    for row in metrics["results"]:
        label = " ".join(f"{k}={row[k]}" for k in ("method", "dim", "noise", "particles") if k in row)
        numbers = "  ".join(f"{k} {v['mean']:.4g} ± {v['se']:.2g}" for k, v in row["per_simulation"].items())
        counts = "  ".join(f"{k} {v}" for k, v in row["counts"].items() if v)
        lines.append(f"  {label:32s} {numbers}  {counts}".rstrip())
    return "\n".join(lines)


def _progress_bar(total: int, done: int, name: str, enabled: bool):
    if enabled:
        from tqdm.auto import tqdm

        return tqdm(total=total, initial=done, desc=name, unit="cell", file=sys.stderr, dynamic_ncols=True)

    class Silent:
        def set_postfix_str(self, text):
            pass

        def update(self, count):
            pass

        def close(self):
            pass

    return Silent()


def load_metrics(out: str) -> dict:
    with open(os.path.join(out, "metrics.json")) as stream:
        return json.load(stream)
