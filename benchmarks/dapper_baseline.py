"""DAPPER baseline for the Lorenz twin-experiment benchmark (speed and rmse.a).

Run with an interpreter that has DAPPER 1.7.1 installed (not ot_filter's), e.g.

    /work/dapper-venv/bin/python benchmarks/dapper_baseline.py --seeds 8

``benchmarks/lorenz_twin.py --dapper-python ...`` runs it in a subprocess and reads its JSON.
This script only calls DAPPER's public API (``dapper.mods`` models, ``dapper.da_methods``).

Configurations (DAPPER's own model files and suggested tunings, same names as lorenz_twin.py):
those of ``ot_filter/experiments/twin_configurations.py`` with a published rmse.a, built from
their ``dapper_method`` call strings. DAPPER's interpreter need not have ot_filter (nor JAX):
that file is loaded by its path and imports neither at import time.

    L63/EnKF-Sqrt-N10     Lorenz63.sakov2012  EnKF('Sqrt', N=10, infl=1.02, rot=True)   0.60
    L63/PartFilt-N800     Lorenz63.sakov2012  PartFilt(N=800, reg=0.9, NER=0.2)         0.28
    L96/EnKF-PertObs-N40  Lorenz96.sakov2008  EnKF('PertObs', N=40, infl=1.06)          0.22
    L96/EnKF-Sqrt-N24     Lorenz96.sakov2008  EnKF('Sqrt', N=24, infl=1.013, rot=True)  0.18

(last column: rmse.a published in DAPPER's model files). Both models run Ko = 1000, i.e. 1001
analyses; L63 integrates 25 RK4 steps of 0.01 between analyses (25,025 steps), L96 one RK4 step
of 0.05 (1,001 steps).

What is measured, per seed s (truth seed s, filter seed s + 100000) and configuration:

- ``seconds``: wall time (``time.perf_counter``) of ``xp.assimilate(HMM, xx, yy)`` only; the truth
  simulation ``HMM.simulate()`` is excluded. DAPPER's per-cycle statistics (``Stats.assess``)
  run inside the assimilation loop and cannot be excluded; by default ``rc.comps['error_only']``
  is set, DAPPER's lightest statistics mode (only the mean and its error are computed; no spread,
  CRPS, rank histogram or singular values). ``--full-stats`` restores DAPPER's default.
- ``rmse_a``: ``xp.avrgs.err.rms.a``, the mean over analysis times t > BurnIn (L63: 16, i.e. 937
  analyses; L96: 20, i.e. 601 analyses) of sqrt(mean_i (mu_i - x_i)^2).

Output: one JSON object on stdout, ``{config: {"seconds": [...], "rmse_a": [...], ...}, "_meta"}``
with one list entry per seed; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import json
import os
import sys
import time

os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np  # noqa: E402

# DAPPER prints a live-plotting warning to stdout at import: keep stdout pure JSON.
with contextlib.redirect_stdout(sys.stderr):
    import dapper as dpr  # noqa: E402
    import dapper.da_methods as da  # noqa: E402
    import dapper.tools.progressbar as progressbar  # noqa: E402
    from dapper.dpr_config import rc  # noqa: E402
    from dapper.mods.Lorenz63.sakov2012 import HMM as HMM_L63  # noqa: E402
    from dapper.mods.Lorenz96.sakov2008 import HMM as HMM_L96  # noqa: E402
    from dapper.tools.seeding import set_seed  # noqa: E402

progressbar.disable_progbar = True
progressbar.disable_user_interaction = True
rc.liveplotting = False
rc.store_u = False

FILTER_SEED_OFFSET = 100_000  # filter seed = truth seed + offset: never reuses a truth seed

MODELS = {"L63": HMM_L63, "L96": HMM_L96}
MODEL_KEYS = {"lorenz63": "L63", "lorenz96": "L96"}




def dapper_method(call: str):
    """DAPPER's method from its call string, e.g. ``"EnKF('Sqrt', N=10, infl=1.02, rot=True)"``
    (a ``dapper.da_methods`` name with literal arguments; parsed, not evaluated)."""
    node = ast.parse(call, mode="eval").body
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)):
        raise ValueError(f"not a DAPPER method call: {call!r}")
    args = [ast.literal_eval(arg) for arg in node.args]
    kwargs = {keyword.arg: ast.literal_eval(keyword.value) for keyword in node.keywords}
    return getattr(da, node.func.id)(*args, **kwargs)


from twin_configurations_by_path import load_twin_configurations  # noqa: E402

CONFIGS = {  # name -> (model, method builder): the configurations DAPPER publishes an rmse.a for
    c.name: (MODEL_KEYS[c.model_name], lambda call=c.dapper_method: dapper_method(call))
    for c in load_twin_configurations().TWIN_CONFIGURATIONS.values()
    if c.expected_rmse is not None
}


def assimilate(HMM, xp, truth, observations, seed: int) -> dict:
    """Runs one DAPPER assimilation; returns its wall time and time-averaged rmse.a."""
    set_seed(seed)
    start = time.perf_counter()
    xp.assimilate(HMM, truth, observations, liveplots=False)
    seconds = time.perf_counter() - start
    xp.stats.average_in_time()
    result = {"seconds": seconds, "rmse_a": float(xp.avrgs.err.rms.a.val)}
    if isinstance(xp, da.PartFilt):  # fraction of analyses that resampled
        result["resample_fraction"] = float(np.nanmean(xp.stats.resmpl[:]))
    return result


def time_dynamics(HMM, num_particles: int, seed: int) -> float:
    """Wall time of DAPPER's model integration alone over the whole run (its Python loop)."""
    set_seed(seed)
    ensemble = HMM.X0.sample(num_particles)
    dt = HMM.tseq.dt
    start = time.perf_counter()
    for k in range(HMM.tseq.K):
        ensemble = HMM.Dyn(ensemble, k * dt, dt)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1, help="number of truths (default 1)")
    parser.add_argument("--first-seed", type=int, default=3000)
    parser.add_argument("--only", default="", help="comma-separated substrings of config names")
    parser.add_argument("--full-stats", action="store_true",
                        help="DAPPER's default statistics instead of error_only")
    parser.add_argument("--time-dynamics", action="store_true",
                        help="also time the bare model integration (no filtering)")
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error("--seeds must be >= 1")
    rc.comps["error_only"] = not args.full_stats

    names = [name for name in CONFIGS
             if not args.only or any(part in name for part in args.only.split(","))]
    results = {
        name: {"seconds": [], "rmse_a": [], "seeds": []} for name in names
    }
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        # One truth per model and seed, shared by all methods (not timed).
        truths = {}
        for experiment, HMM in MODELS.items():
            set_seed(seed)
            truths[experiment] = HMM.simulate()
        for name in names:
            experiment, make_method = CONFIGS[name]
            HMM = MODELS[experiment]
            run = assimilate(HMM, make_method(), *truths[experiment], seed + FILTER_SEED_OFFSET)
            entry = results[name]
            entry["seeds"].append(seed)
            entry["seconds"].append(run["seconds"])
            entry["rmse_a"].append(run["rmse_a"])
            if "resample_fraction" in run:
                entry.setdefault("resample_fraction", []).append(run["resample_fraction"])
            entry["analyses"] = int(HMM.tseq.Ko + 1)
            entry["analyses_averaged"] = int(HMM.tseq.masko.sum())
            entry["model_steps"] = int(HMM.tseq.K)
            print(f"DAPPER seed {seed} {name}: {run['seconds']:.3f} s, "
                  f"rmse.a {run['rmse_a']:.4f}", file=sys.stderr, flush=True)

    if args.time_dynamics:
        results["_dynamics_seconds"] = {
            "L63/N10": time_dynamics(HMM_L63, 10, args.first_seed),
            "L63/N800": time_dynamics(HMM_L63, 800, args.first_seed),
            "L96/N40": time_dynamics(HMM_L96, 40, args.first_seed),
        }
    results["_meta"] = {
        "dapper": dpr.__version__,
        "numpy": np.__version__,
        "python": sys.version.split()[0],
        "seeds": list(range(args.first_seed, args.first_seed + args.seeds)),
        "filter_seed_offset": FILTER_SEED_OFFSET,
        "stats": "full" if args.full_stats else "error_only (DAPPER's lightest stats mode)",
        "timer": "perf_counter around xp.assimilate; Stats.assess runs inside the loop",
    }
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
