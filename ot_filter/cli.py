"""The ``ot-filter`` command (also ``python -m ot_filter``).

    ot-filter list                          the experiments and their options
    ot-filter run EXPERIMENT [options]      run (or resume) one into --out
    ot-filter demo [--out DIR]              Lorenz-63 (EnKF, SIR) and the bimodal example (OT vs EnKF, SIR)
    ot-filter gallery [--out DIR]           every experiment with --quick; their figures into DIR

Errors in names, option values or the output directory are one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import sys
import threading
import time

from ot_filter.experiments.twin_configurations import TWIN_CONFIGURATIONS, TWIN_EXPERIMENTS
from ot_filter.runner.run import RunInterrupted
from ot_filter.runner.store import RunError, write_json_atomic

BURN_IN_ANALYSES = TWIN_EXPERIMENTS["lorenz63"].burn_in  # DAPPER averages after t = 16: 64 analyses


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump)."""

    def error(self, message):
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


class _GracefulInterrupt:
    """Ctrl-C (SIGINT) once: finish the running cell, store it, stop. Twice: stop at once.

    A KeyboardInterrupt raised wherever the interpreter happens to be can be swallowed (e.g. when
    it lands in a garbage-collection callback of JAX: "Exception ignored in ..."), so the first
    signal only sets a flag that the runner polls between cells."""

    def __init__(self):
        self.count = 0
        self.previous = None
        if threading.current_thread() is threading.main_thread():
            self.previous = signal.signal(signal.SIGINT, self._handle)

    def restore(self):
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)

    def _handle(self, signum, frame):
        self.count += 1
        if self.count == 1:
            print("\not-filter: stopping after the running cell (Ctrl-C again to stop now)", file=sys.stderr)
        else:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            raise KeyboardInterrupt

    def requested(self) -> bool:
        return self.count > 0


def _int_list(text: str):
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers separated by commas, got {text!r}") from None
    return values


def _float_list(text: str):
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None


def _names(text: str):
    return tuple(v.strip() for v in text.split(",") if v.strip())


def run_demo(out: str, seed: int = 0) -> dict:
    """Runs the demo, writes ``demo.png`` and ``metrics.json`` under ``out``; returns the metrics."""
    import jax
    import numpy as np

    import ot_filter as otf

    try:
        os.makedirs(out, exist_ok=True)
    except OSError as error:
        raise RunError(f"cannot write to output directory {out!r}: {error.strerror or error}") from None
    experiment = TWIN_EXPERIMENTS["lorenz63"]
    model = experiment.make_model()
    states, observations = otf.simulate(jax.random.key(seed), model, experiment.num_analyses)
    methods = {
        "EnKF (square root, N=10)": TWIN_CONFIGURATIONS["L63/EnKF-Sqrt-N10"],
        "SIR (regularised, N=800)": TWIN_CONFIGURATIONS["L63/PartFilt-N800"],
    }
    results, metrics = {}, {}
    for name, configuration in methods.items():
        update, num_particles = configuration.build_update(), configuration.num_particles
        filter_key = jax.random.key(seed + 1)
        start = time.perf_counter()
        result = otf.run_filter(filter_key, model, update, observations, num_particles, save_every=0)
        result.mean.block_until_ready()
        first = time.perf_counter() - start
        start = time.perf_counter()
        result = otf.run_filter(filter_key, model, update, observations, num_particles, save_every=0)
        result.mean.block_until_ready()
        steady = time.perf_counter() - start
        rmse = np.asarray(otf.metrics.rmse(result.mean, states))
        results[name] = (result, rmse)
        metrics[name] = {
            "rmse_a": float(rmse[BURN_IN_ANALYSES:].mean()),
            "spread_a": float(np.asarray(result.spread)[BURN_IN_ANALYSES:].mean()),
            "seconds_run": steady,
            "seconds_compile": max(first - steady, 0.0),
        }
        print(f"{name:28s} rmse.a {metrics[name]['rmse_a']:.3f}   run {steady * 1e3:7.1f} ms"
              f"   compile {metrics[name]['seconds_compile']:.1f} s")
    _plot_demo(os.path.join(out, "demo.png"), states, observations, results)
    metrics["bimodal"] = _bimodal_demo(out, seed)
    write_json_atomic(os.path.join(out, "metrics.json"), metrics)
    return metrics


# Mini-batches of 256 (both OT filters) instead of ot()'s 1024 at n = 10 keep the demo short.
# Measured with 30 steps (whole demo wall time; global filter's step; its W1): 1024: 167 s, 2.7 s,
# 0.28; 256: 131 s, 0.7 s, 0.33; 128: 113 s, 0.36 s, 0.51 (benchmarks/results/demo_batch/). The
# chapter's 20 steps (t <= 2) since: 97 s, then 59 s with the compiled programs cached; a third
# to a half of a first run is XLA compiling (the two OT filters 11-15 s each). With LLVM level 1
# (CPU_COMPILER_OPTIONS): 91 s, then 53 s (README: the filters in threads gave 60 s, not kept).
BIMODAL_DEMO = dict(dim=10, num_particles=500, num_steps=20, num_simulations=1, ot_options={"batch_size": 256})


def _bimodal_demo(out: str, seed: int) -> dict:
    """The chapter's dynamic example (y = x^2: every coordinate's posterior has two modes) in
    n = 10: the OT filters against EnKF and SIR, scored by W1 to the exact filter."""
    import jax

    from ot_filter.experiments import processes
    from ot_filter.experiments.dynamic_example import run_dynamic_example

    labels = {"enkf": "EnKF", "sir": "SIR", "ot": "OT (global)", "local_ot": "OT (localised)"}
    # The global OT filter in a worker process on the second core, beside the others here.
    in_processes = ("ot",) if jax.default_backend() == "cpu" and processes.available_cores() > 1 else ()
    start = time.perf_counter()
    result = run_dynamic_example(jax.random.key(seed), methods=tuple(labels), keep=1, in_processes=in_processes,
                                 **BIMODAL_DEMO)
    summary, arrays = result["metrics"], result["arrays"]
    metrics = {labels[name]: {"w1": summary[name]["exact"]["w1"]["mean"],
                              "w1_worst_coordinate": summary[name]["exact"]["w1_max"]["mean"],
                              "seconds_per_step": summary[name]["seconds_per_step"]} for name in labels}
    metrics["floor (N exact samples)"] = {"w1": summary["floor"]["w1"]["mean"]}
    for name, values in metrics.items():
        print(f"bimodal n={BIMODAL_DEMO['dim']}: {name:24s} W1 to the exact filter {values['w1']:.3f}")
    print(f"bimodal example: {time.perf_counter() - start:.0f} s with compilation")
    _plot_bimodal_demo(os.path.join(out, "demo_bimodal.png"), arrays, labels, metrics)
    return {**metrics, "settings": dict(BIMODAL_DEMO)}


def _plot_bimodal_demo(path, arrays, labels, metrics):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from ot_filter.experiments._common import save_figure

    times, grid = arrays["times"], arrays["grid"]
    density = arrays["exact_masses"][0, 0] / (grid[1] - grid[0])  # [T, G], coordinate 1
    figure, axes = plt.subplots(1, len(labels), figsize=(4.2 * len(labels), 3.8), sharey=True)
    for ax, (name, label) in zip(axes, labels.items()):
        ax.pcolormesh(times, grid, np.sqrt(density.T), cmap="Greys", shading="nearest")
        particles = arrays[f"{name}_particles"][0][:, :, 0]  # [T, N]
        shown = particles[:, :200]
        ax.plot(np.repeat(times[:, None], shown.shape[1], 1), shown, ".", ms=1, color="tab:orange", alpha=0.4)
        ax.plot(times, arrays["states"][0][:, 0], "b-", lw=1.2, label="truth")
        ax.set(xlabel="time t", ylim=(-3, 3),
               title=f"{label}: W1 {metrics[label]['w1']:.2f}")
    axes[0].set_ylabel("$x_1$ (grey: exact posterior density)")
    axes[0].legend(loc="lower left", fontsize=8)
    figure.suptitle(f"Bimodal example (y = x², n = {BIMODAL_DEMO['dim']}, N = {BIMODAL_DEMO['num_particles']}): "
                    "particles of $x_1$ against the exact filter; W1 averaged over coordinates and t ≥ 1 "
                    f"(floor {metrics['floor (N exact samples)']['w1']:.2f})", fontsize=9)
    save_figure(figure, os.path.dirname(path) or ".", os.path.basename(path))


def _plot_demo(path, states, observations, results):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from ot_filter.experiments._common import save_figure

    times = 0.25 * np.arange(1, states.shape[0] + 1)
    shown = times <= 25.0
    figure, (top, bottom) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=False)
    top.plot(times[shown], np.asarray(states)[shown, 0], "k-", lw=1.5, label="truth")
    top.plot(times[shown], np.asarray(observations)[shown, 0], "k.", ms=3, alpha=0.5,
             label="observations")
    for (name, (result, rmse)), colour in zip(results.items(), ("tab:blue", "tab:red")):
        top.plot(times[shown], np.asarray(result.mean)[shown, 0], "--", color=colour, lw=1.2,
                 label=f"{name} mean")
        bottom.semilogy(times, rmse, color=colour, lw=0.8,
                        label=f"{name}: time-mean RMSE {rmse[BURN_IN_ANALYSES:].mean():.2f}")
    top.set(xlabel="time (model time units)", ylabel="x (first component)",
            title="Lorenz-63 twin experiment: filtering mean vs truth")
    top.legend(loc="upper right", fontsize=8, ncol=2)
    bottom.axvline(16.0, color="grey", ls=":", lw=1)
    bottom.set(xlabel="time (model time units)", ylabel="analysis RMSE",
               title="RMSE over time (average taken after the burn-in, dotted line)")
    bottom.legend(loc="upper right", fontsize=8)
    save_figure(figure, os.path.dirname(path) or ".", os.path.basename(path))


def _list() -> None:
    from ot_filter.runner import EXPERIMENTS

    for experiment in EXPERIMENTS.values():
        print(f"{experiment.name:18s} {experiment.description}")
        defaults = ", ".join(
            f"--{k} {','.join(map(str, v)) if isinstance(v, tuple) else v}"
            for k, v in experiment.defaults.items()
        )
        print(f"{'':18s}   defaults: {defaults}")
        if experiment.sweep:
            print(f"{'':18s}   sweeps over: {', '.join(experiment.sweep)} (comma-separated values)")


def _gallery(out: str, runs: str) -> list[str]:
    """Every experiment with --quick (runs under ``runs``); copies their PNGs into ``out``."""
    from ot_filter.runner import EXPERIMENTS, run_experiment

    try:
        os.makedirs(out, exist_ok=True)
    except OSError as error:
        raise RunError(f"cannot write to output directory {out!r}: {error.strerror or error}") from None
    copied = []
    for name in EXPERIMENTS:
        start = time.perf_counter()
        result = run_experiment(name, out=os.path.join(runs, name), quick=True)
        print(f"{name}: {time.perf_counter() - start:.0f} s")
        for figure in result.figures:
            target = os.path.join(out, f"{name}__{os.path.basename(figure)}")
            shutil.copyfile(figure, target + ".tmp")
            os.replace(target + ".tmp", target)
            copied.append(target)
    return copied


def _use_every_cpu_core() -> None:
    """One single-threaded XLA device per CPU core, so that the experiments' independent
    simulations run side by side (``compile_and_run`` shards them): the OT filter's small matrix
    products gain little from threads, and the chapter's Lorenz-63 OT run takes about half the time.
    Only where JAX has not started yet (a CLI process; not a caller that already computed)."""
    try:  # JAX has no public "started?" query
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:
        return
    if not backends_are_initialized():
        from ot_filter.experiments._common import host_devices_for_cpu_cores

        host_devices_for_cpu_cores()


COMPILE_CACHE_VARIABLE = "OT_FILTER_COMPILE_CACHE"


def compile_cache_directory(environ=os.environ) -> str | None:
    """Where the CLI keeps compiled programs between runs: ``$OT_FILTER_COMPILE_CACHE`` (empty or
    ``off``: no cache), else ``$XDG_CACHE_HOME/ot_filter/jax`` (``~/.cache/ot_filter/jax``)."""
    chosen = environ.get(COMPILE_CACHE_VARIABLE)
    if chosen is not None:
        return None if chosen.strip() in ("", "off") else chosen
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "ot_filter", "jax")


def use_compile_cache(directory: str | None) -> None:
    """JAX's persistent compilation cache in ``directory`` (None: none), unless the caller set
    one (``JAX_COMPILATION_CACHE_DIR``). XLA's compilation is a third to a half of a short run on
    a CPU (the demo's two OT filters compile for 11-15 s each): a repeated run reads the programs
    back instead (the demo's bimodal part: 86 s, then 52 s)."""
    import jax

    if directory is None or jax.config.jax_compilation_cache_dir:
        return
    jax.config.update("jax_compilation_cache_dir", directory)


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog="ot-filter", description="Experiments of the ot_filter toolkit.")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    commands.add_parser("list", help="list the experiments and their default options")
    run = commands.add_parser("run", help="run (or resume) an experiment")
    run.add_argument("experiment", help="an experiment name (ot-filter list)")
    run.add_argument("--particles", type=_int_list, help="N, or N1,N2,... for a sweep")
    run.add_argument("--dim", type=_int_list, help="state dimension n, or n1,n2,... for a sweep")
    run.add_argument("--steps", type=int, help="time steps T")
    run.add_argument("--simulations", type=int, help="independent simulations S")
    run.add_argument("--block", type=int, help="simulations per stored cell (resume granularity)")
    run.add_argument("--seed", type=int, help="PRNG seed K")
    run.add_argument("--methods", type=_names, help="comma-separated, e.g. enkf,sir,ot")
    run.add_argument("--noise", type=_float_list, help="observation noise levels (static example)")
    run.add_argument("--dt", type=float, help="time step (continuous-time experiments)")
    run.add_argument("--out", help="output directory (default ot-filter-runs/EXPERIMENT)")
    run.add_argument("--maps", help="amortised OT maps (methods amortised, amortised_warm, amortised_distilled, "
                                    "local_amortised, local_amortised_warm): read from here if trained before for "
                                    "this model, else trained and stored here (default OUT/maps)")
    run.add_argument("--map-iterations", dest="map_iterations", type=int,
                     help="offline training iterations of an amortised OT map (of each candidate), its distilled "
                          "student or a local map that is not stored yet")
    run.add_argument("--map-gate", dest="map_gate", type=float,
                     help="global amortised OT maps (methods amortised, amortised_warm, amortised_distilled): the most "
                          "the kept map's (a) MSE may be, as a multiple of the online OT filter's on held-out truths, "
                          "before the offline stage trains further candidates (0: no gate; default: the experiment's, "
                          "Lorenz-63 1.25, the dynamic example none; none with --quick)")
    run.add_argument("--quick", action="store_true", help="small settings: under two minutes on 2 cores")
    run.add_argument("--no-progress", action="store_true", help="no progress bar or step reports")
    demo = commands.add_parser("demo", help="Lorenz-63 with EnKF and SIR, and the bimodal example where the OT "
                                            "filters hold both modes (about 1.5 minutes; 1 once compiled)")
    demo.add_argument("--out", default="ot-filter-demo", help="output directory")
    demo.add_argument("--seed", type=int, default=0)
    gallery = commands.add_parser("gallery", help="every experiment with --quick; figures into --out")
    gallery.add_argument("--out", default="docs/gallery", help="where the PNGs go")
    gallery.add_argument("--runs", default="ot-filter-runs/gallery", help="where the runs go")
    arguments = parser.parse_args(argv)
    if argv is None and arguments.command != "list":  # a CLI process, not a caller's main([...])
        _use_every_cpu_core()
        use_compile_cache(compile_cache_directory())
    try:
        if arguments.command == "list":
            _list()
        elif arguments.command == "demo":
            run_demo(arguments.out, arguments.seed)
            print(f"wrote {os.path.join(arguments.out, 'demo.png')}, "
                  f"{os.path.join(arguments.out, 'demo_bimodal.png')} and "
                  f"{os.path.join(arguments.out, 'metrics.json')}")
        elif arguments.command == "gallery":
            copied = _gallery(arguments.out, arguments.runs)
            print(f"wrote {len(copied)} figures to {arguments.out}")
        else:
            from ot_filter.runner import run_experiment

            overrides = {k: getattr(arguments, k) for k in
                         ("particles", "dim", "steps", "simulations", "block", "seed", "methods", "noise", "dt",
                          "map_iterations", "map_gate", "maps")}
            stop = _GracefulInterrupt()
            try:
                result = run_experiment(arguments.experiment, overrides, arguments.out, arguments.quick,
                                        progress=not arguments.no_progress,
                                        command=["ot-filter", *(argv if argv is not None else sys.argv[1:])],
                                        stop_requested=stop.requested)
            finally:
                stop.restore()
            print(f"ran {result.cells_run} cells ({result.cells_skipped} already finished); "
                  f"outputs in {result.out}: config.json, metrics.json, timings.json, arrays.npz, "
                  + ", ".join(os.path.basename(f) for f in result.figures))
    except (RunError, OSError) as error:
        print(f"ot-filter: error: {error}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, RunInterrupted):
        print("ot-filter: interrupted; finished cells are kept, rerun the same command to resume",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
