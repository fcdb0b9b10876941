"""DAPPER baseline for the LETKF on Lorenz-96 (speed and rmse.a), with the truths saved for reuse.

Run with an interpreter that has DAPPER 1.7.1 installed (not ot_filter's), e.g.

    /tmp/dapper-venv/bin/python benchmarks/dapper_letkf_baseline.py --setting sakov2008 \\
        --methods "LETKF(N=7, rot=True, infl=1.04, loc_rad=4)" --seeds 8 \\
        --save-truths /tmp/letkf_truths_sakov2008.npz

This script only calls DAPPER's public API (``dapper.mods`` models, ``dapper.da_methods``).
``--methods`` takes DAPPER call strings (a ``dapper.da_methods`` name with literal arguments;
parsed, not evaluated), separated by ``;`` or given by repeating the flag; global methods work
too, e.g. ``"EnKF('Sqrt', N=20, infl=1.02, rot=True)"``.

Settings (DAPPER's own Lorenz-96 model files, imported unchanged; Nx = 40, F = 8, RK4):

    sakov2008  dapper.mods.Lorenz96.sakov2008: all 40 components observed, R = 1 * I (variance),
               dt = dto = 0.05 (dko = 1), Ko = 1000 (1001 analyses, K = 1001 steps),
               BurnIn = 20 time units (601 analyses averaged), X0 = N(x0, 0.001 I) with
               x0 = e_0 (1 at index 0, else 0), no model noise, localizer batches of 2.
               DAPPER's comment: LETKF(N=7, rot=True, infl=1.04, loc_rad=4) -> rmse.a 0.22.
    sparse     dapper.mods.Lorenz96.spantini2019 (the file that matches the issue: every second
               component observed, obs_inds = 0, 2, ..., 38; noise 0.5; dto = 0.4):
               dt = 0.02, dko = 20, Ko = 2000 (2001 analyses, K = 40020 steps),
               BurnIn = 20 time units (1951 analyses averaged), X0 = N(x0, 0.1 I),
               no model noise, localizer batches of 2.
               DAPPER's comments: LETKF(N=40, infl=1.10, loc_rad=4) -> 1.0,
               LETKF(N=60, infl=1.02, loc_rad=4) -> 0.89, LETKF(N=100, infl=1.02, loc_rad=4)
               -> 0.84; EnKF('Sqrt', N=40/60/100, infl=1.10) -> 2.2 / 1.3 / 0.97.

Noise convention: DAPPER's scalar ``Obs["noise"] = 0.5`` is ``GaussRV(C=0.5)``, i.e. the
observation-error VARIANCE is 0.5 (std sqrt(0.5) = 0.7071). The ``sparse`` setting keeps that
convention because it is DAPPER's own file (reproducing Spantini et al.'s Lorenz-96 setup), whose
published LETKF/EnKF numbers above only hold for it. ``--obs-noise-var 0.25`` gives the other
reading of "noise 0.5" (std 0.5); DAPPER's numbers do not apply then. The npz records both the
variance and the std actually used.

What is measured, per seed s (truth seed s, filter seed s + 100000) and method:

- ``seconds``: wall time (``time.perf_counter``) of ``xp.assimilate(HMM, xx, yy)`` only; the truth
  simulation ``HMM.simulate()`` is excluded. DAPPER's per-step statistics (``Stats.assess``, called
  at every model step, not only at analyses) run inside the loop; by default
  ``rc.comps['error_only']`` is set (DAPPER's lightest statistics mode); ``--full-stats`` restores
  DAPPER's default. Progress bars are off unless ``--progbar`` (DAPPER's default is on; the tqdm
  bars go to stderr).
- ``seconds_per_analysis``: ``seconds / (Ko + 1)`` (includes the model steps between analyses).
- ``rmse_a`` / ``rmse_f``: ``xp.avrgs.err.rms.a`` / ``.f``, the mean over the analysis times
  t > BurnIn (``HMM.tseq.masko``) of sqrt(mean_i (mu_i - x_i)^2).

Time indexing (DAPPER's ``Chronology``): ``xx`` has K + 1 rows, ``xx[0]`` is t = 0 (drawn from X0);
``yy`` has Ko + 1 rows, ``yy[ko]`` observes ``xx[kko[ko]]`` with ``kko = dko * (1 + arange(Ko+1))``
(no observation at t = 0; the filter starts with a forecast from an ensemble drawn from X0,
independently of ``xx[0]``). rmse.a averages the analyses ``ko`` with ``masko[ko]`` (t > BurnIn,
strict), i.e. ``ko >= ioBurnIn``.

``--save-truths PATH`` writes an npz (``np.savez_compressed``) with, for S seeds:

    xx [S, K+1, Nx]  truths          yy [S, Ko+1, Ny]  observations       seeds [S]
    kko [Ko+1]  xx row of each yy row        masko [Ko+1]  analyses averaged in rmse.a
    ioBurnIn  first averaged ko              BurnIn  burn-in time (strict t > BurnIn)
    dt  model step   dko  steps between obs  dto  time between obs   K, Ko, num_analyses (Ko+1)
    obs_inds [Ny]    obs_noise_var, obs_noise_std (scalars; R = obs_noise_var * I)
    x0_mean [Nx], x0_var (X0 = N(x0_mean, x0_var I))   forcing (8.0)   model_noise_var (0)
    loc_batches [20, 2]  DAPPER's localization batches (state indices analysed together)
    setting, dapper_version (strings)

DAPPER's runs are slow (sakov2008 LETKF N=7: ~10 s per seed; sparse LETKF N=100: ~45 s per
seed on one core), so a long run can be split into invocations with ``--first-seed`` and
``--append-truths`` (which checks the metadata and adds the new seeds to the npz).

Output: one JSON object on stdout, ``{method: {"seconds": [...], "rmse_a": [...], ...}, "_meta"}``
with one list entry per seed; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time

os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np  # noqa: E402

# The DAPPER set-up (quiet imports, no progress bars or live plots, the filter seed offset) and
# the call-string parser are the Lorenz twin baseline's, in this folder.
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from dapper_baseline import (  # noqa: E402
    FILTER_SEED_OFFSET,
    dapper_method,
    dpr,
    progressbar,
    rc,
    set_seed,
)

with contextlib.redirect_stdout(sys.stderr):  # DAPPER's import-time warning stays off stdout
    import dapper.mods as modelling  # noqa: E402
    from dapper.mods.Lorenz96 import Force  # noqa: E402
    from dapper.mods.Lorenz96.sakov2008 import HMM as HMM_SAKOV2008  # noqa: E402
    from dapper.mods.Lorenz96.spantini2019 import HMM as HMM_SPANTINI2019  # noqa: E402

SETTINGS = {  # name -> (DAPPER HMM, its model file)
    "sakov2008": (HMM_SAKOV2008, "dapper.mods.Lorenz96.sakov2008"),
    "sparse": (HMM_SPANTINI2019, "dapper.mods.Lorenz96.spantini2019"),
}


NPZ_ONLY = ("kko", "masko", "loc_batches", "x0_mean")  # metadata left out of the JSON


def make_hmm(setting: str, obs_noise_var: float | None, Ko: int | None):
    """A copy of the setting's HMM, optionally with another R = var * I or run length Ko."""
    HMM = SETTINGS[setting][0].copy()
    if obs_noise_var is not None:
        obs = HMM.Obs(0)
        obs.noise = modelling.GaussRV(C=obs_noise_var, M=obs.M)
    if Ko is not None:
        HMM.tseq.Ko = Ko  # Chronology setter: keeps dt, dko, BurnIn
    return HMM


def setting_metadata(HMM, setting: str) -> dict:
    """Arrays and scalars describing the HMM, for the npz (and, as lists, the JSON)."""
    tseq, obs = HMM.tseq, HMM.Obs(0)
    Nx = HMM.Dyn.M
    obs_inds = np.flatnonzero(np.asarray(obs.linear(np.zeros(Nx))).any(axis=0))
    # partial_Id_Obs: H = I[obs_inds]; check the operator is that selection.
    assert np.array_equal(obs(np.arange(Nx, dtype=float)), obs_inds.astype(float))
    R = obs.noise.C.full
    obs_noise_var = float(np.round(R[0, 0], 12))  # C.full is rebuilt from an EVD: round-off
    assert np.allclose(R, obs_noise_var * np.eye(obs.M)), "R is not a multiple of I"
    x0_cov = HMM.X0.C.full
    x0_var = float(np.round(x0_cov[0, 0], 12))
    assert np.allclose(x0_cov, x0_var * np.eye(Nx)), "X0 covariance is not a multiple of I"
    batches, _ = obs.localizer(1.0, "x2y", "GC")
    return {
        "setting": setting,
        "dapper_model": SETTINGS[setting][1],
        "dt": float(tseq.dt),
        "dko": int(tseq.dko),
        "dto": float(tseq.dto),
        "K": int(tseq.K),
        "Ko": int(tseq.Ko),
        "num_analyses": int(tseq.Ko + 1),
        "kko": np.asarray(tseq.kko),
        "masko": np.asarray(tseq.masko),
        "ioBurnIn": int(tseq.ioBurnIn),
        "BurnIn": float(tseq.BurnIn),
        "num_analyses_averaged": int(tseq.masko.sum()),
        "Nx": int(Nx),
        "obs_inds": obs_inds,
        "obs_noise_var": obs_noise_var,
        "obs_noise_std": float(np.sqrt(obs_noise_var)),
        "x0_mean": np.asarray(HMM.X0.mu, dtype=float),
        "x0_var": x0_var,
        "forcing": float(Force),
        "model_noise_var": float(np.max(HMM.Dyn.noise.C.full)) if HMM.Dyn.noise.C != 0 else 0.0,
        "loc_batches": np.asarray(batches),
        "dapper_version": dpr.__version__,
    }


def save_truths(path: str, xx, yy, seeds: list[int], meta: dict, append: bool) -> None:
    """Writes the truths and metadata; with ``append``, adds new seeds to an existing file of the
    same setting (so that long runs can be split into short invocations)."""
    if append and os.path.exists(path):
        with np.load(path) as old:
            for key, value in meta.items():
                if not np.array_equal(old[key], np.asarray(value)):
                    raise SystemExit(f"{path}: {key} differs from this run's; not appending")
            if set(old["seeds"].tolist()) & set(seeds):
                raise SystemExit(f"{path} already holds some of seeds {seeds}; not appending")
            xx = np.concatenate([old["xx"], xx])
            yy = np.concatenate([old["yy"], yy])
            seeds = old["seeds"].tolist() + list(seeds)
    np.savez_compressed(path, xx=xx, yy=yy, seeds=np.asarray(seeds), **meta)
    print(f"saved truths of seeds {seeds} to {path}", file=sys.stderr, flush=True)


def assimilate(HMM, xp, truth, observations, seed: int) -> dict:
    """Runs one DAPPER assimilation; returns its wall time and time-averaged rmse.a / rmse.f."""
    set_seed(seed)
    start = time.perf_counter()
    xp.assimilate(HMM, truth, observations, liveplots=False)
    seconds = time.perf_counter() - start
    xp.stats.average_in_time()
    return {
        "seconds": seconds,
        "rmse_a": float(xp.avrgs.err.rms.a.val),
        "rmse_f": float(xp.avrgs.err.rms.f.val),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--setting", choices=sorted(SETTINGS), default="sakov2008")
    parser.add_argument("--methods", action="append", required=True,
                        help="DAPPER method call strings, ';'-separated (or repeat the flag)")
    parser.add_argument("--seeds", type=int, default=1, help="number of truths (default 1)")
    parser.add_argument("--first-seed", type=int, default=3000)
    parser.add_argument("--save-truths", default="", help="npz path for the truths and metadata")
    parser.add_argument("--append-truths", action="store_true",
                        help="add this run's seeds to an existing --save-truths file")
    parser.add_argument("--progbar", action="store_true",
                        help="leave DAPPER's progress bars on (stderr), as in DAPPER's default")
    parser.add_argument("--full-stats", action="store_true",
                        help="DAPPER's default statistics instead of error_only")
    parser.add_argument("--obs-noise-var", type=float, default=None,
                        help="override R = VAR * I (DAPPER's noise is a variance)")
    parser.add_argument("--Ko", type=int, default=None,
                        help="override the number of analyses minus one (shorter runs)")
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error("--seeds must be >= 1")
    rc.comps["error_only"] = not args.full_stats
    progressbar.disable_progbar = not args.progbar

    methods = [call.strip() for group in args.methods for call in group.split(";") if call.strip()]
    for call in methods:
        dapper_method(call)  # fail early on a bad call string

    HMM = make_hmm(args.setting, args.obs_noise_var, args.Ko)
    meta = setting_metadata(HMM, args.setting)
    num_analyses = meta["num_analyses"]
    print(f"DAPPER {args.setting}: K={meta['K']} steps of dt={meta['dt']}, "
          f"{num_analyses} analyses every {meta['dto']}, Ny={len(meta['obs_inds'])}, "
          f"R={meta['obs_noise_var']}*I, {meta['num_analyses_averaged']} averaged",
          file=sys.stderr, flush=True)

    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    results = {call: {"seconds": [], "seconds_per_analysis": [], "rmse_a": [], "rmse_f": [],
                      "seeds": []} for call in methods}
    truths, observations = [], []
    for seed in seeds:
        set_seed(seed)  # one truth per seed, shared by all methods (not timed)
        xx, yy = HMM.simulate()
        yy = np.stack([np.asarray(y, dtype=float) for y in yy])  # object array -> [Ko+1, Ny]
        truths.append(xx)
        observations.append(yy)
        for call in methods:
            run = assimilate(HMM, dapper_method(call), xx, yy, seed + FILTER_SEED_OFFSET)
            entry = results[call]
            entry["seeds"].append(seed)
            entry["seconds"].append(run["seconds"])
            entry["seconds_per_analysis"].append(run["seconds"] / num_analyses)
            entry["rmse_a"].append(run["rmse_a"])
            entry["rmse_f"].append(run["rmse_f"])
            print(f"DAPPER seed {seed} {call}: {run['seconds']:.3f} s "
                  f"({1e3 * run['seconds'] / num_analyses:.3f} ms/analysis), "
                  f"rmse.a {run['rmse_a']:.4f}", file=sys.stderr, flush=True)
    for entry in results.values():
        entry["rmse_a_mean"] = float(np.mean(entry["rmse_a"]))
        entry["seconds_mean"] = float(np.mean(entry["seconds"]))

    if args.save_truths:
        save_truths(args.save_truths, np.stack(truths), np.stack(observations), seeds, meta,
                    append=args.append_truths)

    results["_meta"] = {
        **{key: (value.tolist() if isinstance(value, np.ndarray) else value)
           for key, value in meta.items() if key not in NPZ_ONLY},
        "numpy": np.__version__,
        "python": sys.version.split()[0],
        "seeds": seeds,
        "filter_seed_offset": FILTER_SEED_OFFSET,
        "progbar": args.progbar,
        "stats": "full" if args.full_stats else "error_only (DAPPER's lightest stats mode)",
        "timer": "perf_counter around xp.assimilate; Stats.assess runs inside the loop",
        "truths_npz": args.save_truths or None,
    }
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
