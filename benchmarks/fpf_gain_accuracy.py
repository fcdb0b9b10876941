"""Accuracy of the kernel (diffusion-map) FPF gain vs the particle count N, in 1-D, against exact gains.

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false" taskset -c 1 \
        /work/venv/bin/python benchmarks/fpf_gain_accuracy.py [--quick] [--out benchmarks/results/fpf_gain_accuracy]

Two densities with h(x) = x (observation noise 1), where the exact gain K = phi' is known:
- gaussian: N(0, 1); K = 1 everywhere.
- bimodal: 0.5 N(-1, 0.5^2) + 0.5 N(1, 0.5^2) (density in the trough at 0 is 27% of the peaks');
  K by quadrature (``reference.poisson_gain_1d`` on a 20001-point grid), interpolated to the particles.

Error of one ensemble: RMS over its particles of K_N(X^i) - K(X^i) (``kernel_gain(...).apply``'s
``output.gain``), averaged over independent seeds (mean +- s.e.; 32 seeds for N <= 500, 16 up to
2000, 8 at 4000, 4 at 8000). Series over N in {125, 250, ..., 4000} and 8000:
- fixed eps = 0.1 and eps = 0.05 (expected: N^{-1/2} decay down to an O(eps) floor);
- eps = 0.1 (N / 1000)^{-1/5} and eps = 0.1 (N / 1000)^{-2/5} (eps is in squared state units, so
  the second is the classical bandwidth rule sqrt(eps) ~ N^{-1/5} of kernel estimators).
Also: an eps sweep at N = 1000; the bias / spread split of the error (errors of all seeds pooled,
binned by x: the RMS of the bin means is the bias, the RMS within-bin standard deviation the spread);
the N = infinity limit of the algorithm for each eps (the same formulas with the density as weights
on a fine grid; closed form for the Gaussian), i.e. the eps-bias floor; the gain formula with
r = Phi + eps h (the library) vs Phi alone (the notes), computed here from the library's fixed point;
the solver iterations used (info.iterations) and whether they converged. Particles are the same
for every eps (common random numbers). float64 throughout.

Writes results.json, table.md and gain_error_vs_particles.png to --out (``--quick``: tiny settings,
about 25 s, to benchmarks/results/fpf_gain_accuracy/quick unless --out is given; ``--replot``:
rewrite table.md and the figure from an existing results.json). The full run takes about 7.5
minutes on one core (1.9 GB peak memory).
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import os
import subprocess
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from ot_filter.continuous import kernel_gain  # noqa: E402
from ot_filter.experiments._common import save_figure, stats, write_text_atomic  # noqa: E402
from ot_filter.reference import grid_posterior, poisson_gain_1d  # noqa: E402

KEY = 2026
CASES = ("gaussian", "bimodal")
BIMODAL_MEAN, BIMODAL_STD = 1.0, 0.5
# A generous cap: with plain fixed-point sweeps a nearly isolated tail particle (T_ii = 1 - delta) needed
# ~ log(1/tol) / delta sweeps (17418 for one ensemble at N = 4000, eps = 0.1, tolerance 1e-6).
TOLERANCE, MAX_ITERATIONS = 1e-5, 3000
# The library's default cap, for the count of runs that would exceed it.
DEFAULT_MAX_ITERATIONS = inspect.signature(kernel_gain).parameters["max_iterations"].default
ANCHOR_COUNT, ANCHOR_EPS = 1000, 0.1  # eps schedules pass through eps = 0.1 at N = 1000


def log_density(case: str, x):
    """Unnormalised log density (NumPy or JAX arrays)."""
    xp = jnp if isinstance(x, jax.Array) else np
    if case == "gaussian":
        return -0.5 * x**2
    z = (x - BIMODAL_MEAN) / BIMODAL_STD, (x + BIMODAL_MEAN) / BIMODAL_STD
    return xp.logaddexp(-0.5 * z[0] ** 2, -0.5 * z[1] ** 2)


def sample(case: str, key, num: int):
    """``num`` particles [num, 1] from the case's density."""
    normal_key, mode_key = jax.random.split(key)
    z = jax.random.normal(normal_key, (num, 1))
    if case == "gaussian":
        return z
    sign = jnp.where(jax.random.bernoulli(mode_key, 0.5, (num, 1)), 1.0, -1.0)
    return sign * BIMODAL_MEAN + BIMODAL_STD * z


class ExactGain:
    """K on a fine grid by quadrature (``poisson_gain_1d``); ``__call__`` interpolates.

    ``poisson_gain_1d`` integrates the flux from the left end, K(x) = -(1/p) int_{-inf}^x (h - h_hat) p:
    right of the median that is a difference of nearly equal numbers divided by a small p, which
    loses all accuracy in the right tail (K(6) ~ 6e5 instead of ~0.31 for the bimodal case). So the
    right half is taken from the mirrored problem (p(-x), h(-x)), whose flux starts from the right
    end: phi(x) = psi(-x) gives K(x) = -K_mirrored(-x)."""

    def __init__(self, case: str, num_points: int = 20_001, width: float = 7.0):
        density = grid_posterior(lambda x: log_density(case, x), -width, width, num_points)
        mirrored = grid_posterior(lambda x: log_density(case, -x), -width, width, num_points)
        self.grid = np.asarray(density.grid)
        left = np.asarray(poisson_gain_1d(density, density.grid))
        right = -np.asarray(poisson_gain_1d(mirrored, -mirrored.grid))[::-1]
        self.values = np.where(np.asarray(density.cdf) <= 0.5, left, right)
        self.left_only = left
        self.case = case

    def __call__(self, x):
        if self.case == "gaussian":
            return np.ones_like(x)  # exact; the quadrature's deviation from 1 is recorded separately
        return np.interp(x, self.grid, self.values)


def gaussian_limit_gain(eps: float) -> tuple[float, float]:
    """N = infinity gain of the algorithm for N(0, 1) and h = x, in closed form: T maps x to c x with
    c = (1 + 2 eps) / (1 + 3 eps + 4 eps^2), T(x, .) has variance v = 2 eps c, the fixed point is
    Phi = eps x / (1 - c), r = Phi + eps x, and K = Cov_T(X, .) / (2 eps): K_r = v (1 / (1 - c) + 1) / 2
    and K_Phi = v / (2 (1 - c)) (constants: K_r = 1 - eps + O(eps^2), K_Phi = 1 - 2 eps + O(eps^2))."""
    c = (1 + 2 * eps) / (1 + 3 * eps + 4 * eps**2)
    v = 2 * eps * c
    return v * (1 / (1 - c) + 1) / 2, v / (2 * (1 - c))


def limit_gain_error(case: str, eps: float, exact: ExactGain, num_points: int = 2001,
                     width: float = 7.0) -> dict:
    """The algorithm at N = infinity: particles replaced by a grid weighted by the density
    (T(x, dy) = k(x, y) p(y) dy / int k(x, z) p(z) dz), the mean-centred fixed point solved exactly.
    Returns the p-weighted RMS of K_eps - K for r = Phi + eps h and for Phi alone: the eps-bias floor
    that the error at fixed eps tends to as N grows."""
    x = np.linspace(-width, width, num_points)
    w = np.exp(log_density(case, x) - np.max(log_density(case, x)))
    w /= w.sum()
    g = np.exp(-((x[:, None] - x[None, :]) ** 2) / (4 * eps))
    degree = g @ w
    k = g / np.sqrt(degree[:, None] * degree[None, :])
    markov = k * w[None, :]
    markov /= markov.sum(axis=1, keepdims=True)
    forcing = eps * (x - w @ x)
    centring = np.eye(num_points) - np.outer(np.ones(num_points), w)
    potential = np.linalg.solve(np.eye(num_points) - centring @ markov, centring @ forcing)

    def formula(values):
        return (markov @ (x * values) - (markov @ x) * (markov @ values)) / (2 * eps)

    target = exact(x)
    gain_r, gain_phi = formula(potential + forcing), formula(potential)
    out = {"rms_r": float(np.sqrt(w @ (gain_r - target) ** 2)),
           "rms_phi": float(np.sqrt(w @ (gain_phi - target) ** 2))}
    if case == "gaussian":
        closed_r, closed_phi = gaussian_limit_gain(eps)
        central = np.abs(x) < 3
        out.update(closed_form_r=closed_r, closed_form_phi=closed_phi,
                   grid_vs_closed_form_max_abs=float(max(np.max(np.abs(gain_r[central] - closed_r)),
                                                         np.max(np.abs(gain_phi[central] - closed_phi)))))
    return out


def markov_matrix(particles, eps):
    """The library's T (same formulas), rebuilt here for the Phi-only variant of the gain formula."""
    squared = jnp.sum(particles**2, axis=1)
    distances = jnp.maximum(squared[:, None] + squared[None, :] - 2 * particles @ particles.T, 0.0)
    g = jnp.exp(-distances / (4 * eps))
    degree = jnp.sum(g, axis=1)
    k = g / jnp.sqrt(degree[:, None] * degree[None, :])
    return k / jnp.sum(k, axis=1, keepdims=True)


def gain_formula(markov, particles, values, eps):
    """(1 / (2 eps)) [T (x v) - (T x)(T v)] at the particles (1-D, one observation)."""
    x, v = particles[:, 0], values[:, 0]
    return (markov @ (x * v) - (markov @ x) * (markov @ v)) / (2 * eps)


def make_runner(eps: float):
    """Jitted ``(key, particles) -> dict`` for one eps: the library's gain and diagnostics, the
    Phi-only gain from the library's fixed point, and the gap between the library's gain and this
    file's re-implementation of the r formula (a check that the two read the formula alike)."""
    gain = kernel_gain(epsilon=eps, tolerance=TOLERANCE, max_iterations=MAX_ITERATIONS)

    def run(key, particles):
        h_values = particles  # h(x) = x
        state = gain.init(key, particles, h_values)
        output, state, info = gain.apply(key, state, particles, h_values)
        markov = markov_matrix(particles, eps)
        potential = state.potential
        forcing = eps * (h_values - jnp.mean(h_values, axis=0))
        library = output.gain[:, 0, 0]
        gain_r = gain_formula(markov, particles, potential + forcing, eps)
        return {
            "gain": library,
            "gain_phi": gain_formula(markov, particles, potential, eps),
            "reimplementation_gap": jnp.max(jnp.abs(gain_r - library)),
            "iterations": info.iterations,
            "converged": info.converged,
            "fallback": info.fallback,
        }

    return jax.jit(run)


def bias_and_spread(positions: np.ndarray, errors: np.ndarray, num_bins: int) -> dict:
    """Pooled errors binned by position (equal-count bins): bias = RMS of the bin means (each
    squared mean less its sampling variance var/n), spread = RMS within-bin standard deviation."""
    order = np.argsort(positions)
    bins = np.array_split(errors[order], num_bins)
    total = errors.size
    bias2 = sum(b.size * (b.mean() ** 2 - b.var(ddof=1) / b.size) for b in bins) / total
    spread2 = sum(b.size * b.var(ddof=1) for b in bins) / total
    return {"bias": float(np.sqrt(max(bias2, 0.0))), "spread": float(np.sqrt(spread2)),
            "bins": num_bins}


def fit_slope(counts, values) -> dict:
    """Least-squares slope of log(values) on log(counts), with its standard error."""
    logn, logv = np.log(np.asarray(counts, float)), np.log(np.asarray(values, float))
    if logn.size < 2:
        return {"slope": float("nan"), "stderr": float("nan")}
    if logn.size == 2:
        return {"slope": float((logv[1] - logv[0]) / (logn[1] - logn[0])), "stderr": float("nan")}
    coefficients, covariance = np.polyfit(logn, logv, 1, cov=True)
    return {"slope": float(coefficients[0]), "stderr": float(np.sqrt(covariance[0, 0]))}


class Study:
    """Runs (case, N, seed, eps) once each, caching per-run summaries and compiled runners."""

    def __init__(self, exact: dict):
        self.exact = exact
        self.runners: dict = {}
        self.runs: dict = {}
        self.compile_s = 0.0
        self.max_reimplementation_gap = 0.0

    def runner(self, eps, particles, key):
        if eps not in self.runners:
            self.runners[eps] = make_runner(eps)
        shapes = (eps, particles.shape[0])
        if shapes not in self.runners:
            start = time.perf_counter()
            self.runners[shapes] = self.runners[eps].lower(key, particles).compile()
            self.compile_s += time.perf_counter() - start
        return self.runners[shapes]

    def run(self, case, num, seed, eps):
        name = (case, num, seed, eps)
        if name not in self.runs:
            key = jax.random.fold_in(jax.random.fold_in(jax.random.fold_in(
                jax.random.key(KEY), CASES.index(case)), num), seed)
            particles = sample(case, key, num)
            out = jax.tree.map(np.asarray, self.runner(eps, particles, key)(key, particles))
            x = np.asarray(particles[:, 0])
            target = self.exact[case](x)
            fallback = bool(out["fallback"])
            if not fallback:
                self.max_reimplementation_gap = max(self.max_reimplementation_gap,
                                                    float(out["reimplementation_gap"]))
            self.runs[name] = {
                "x": x,
                "error": out["gain"] - target,
                "error_phi": out["gain_phi"] - target if not fallback else np.full(num, np.nan),
                "iterations": int(out["iterations"]),
                "converged": bool(out["converged"]),
                "fallback": fallback,
            }
        return self.runs[name]

    def summarise(self, case, num, eps, seeds) -> dict:
        """Accuracy over the seeds whose fixed point converged (the others got the library's
        constant-gain fallback, counted in ``fallbacks``; ``rms_as_delivered`` includes them)."""
        every = [self.run(case, num, seed, eps) for seed in range(seeds)]
        runs = [r for r in every if r["converged"] and not r["fallback"]] or every
        rms = [np.sqrt(np.mean(r["error"] ** 2)) for r in runs]
        rms_phi = [np.sqrt(np.mean(r["error_phi"] ** 2)) for r in runs]
        iterations = [r["iterations"] for r in every]
        positions = np.concatenate([r["x"] for r in runs])
        errors = np.concatenate([r["error"] for r in runs])
        return {
            "eps": eps,
            "seeds": seeds,
            "seeds_used": len(runs),
            "rms": stats(rms),
            "rms_median": float(np.median(rms)),
            "rms_per_seed": [float(v) for v in rms],
            "max_abs_error": float(max(np.max(np.abs(r["error"])) for r in runs)),
            "rms_phi_only": stats(rms_phi),
            "rms_as_delivered": stats([np.sqrt(np.mean(r["error"] ** 2)) for r in every]),
            "split": bias_and_spread(positions, errors, max(2, min(40, errors.size // 50))),
            "iterations_mean": float(np.mean(iterations)),
            "iterations_max": int(np.max(iterations)),
            "converged_fraction": float(np.mean([r["converged"] for r in every])),
            "fallbacks": int(sum(r["fallback"] for r in every)),
            "over_default_cap": int(sum(i > DEFAULT_MAX_ITERATIONS for i in iterations)),
        }


def series_definitions(counts, extra_count):
    """name -> (label, eps(N), counts)."""
    counts = counts + ([extra_count] if extra_count else [])
    return {
        "eps_0.1": ("eps = 0.1", lambda n: 0.1, counts),
        "eps_0.05": ("eps = 0.05", lambda n: 0.05, counts),
        "eps_N^-1/5": ("eps = 0.1 (N/1000)^-1/5",
                       lambda n: round(ANCHOR_EPS * (n / ANCHOR_COUNT) ** (-1 / 5), 6), counts),
        "eps_N^-2/5": ("eps = 0.1 (N/1000)^-2/5",
                       lambda n: round(ANCHOR_EPS * (n / ANCHOR_COUNT) ** (-2 / 5), 6), counts),
    }


def seeds_for(num: int, quick: bool) -> int:
    if quick:
        return 3
    return 32 if num <= 500 else (16 if num <= 2000 else (8 if num <= 4000 else 4))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny settings (< 1 minute)")
    parser.add_argument("--counts", default=None, help="particle counts, comma-separated")
    parser.add_argument("--extra-count", type=int, default=None,
                        help="one more N, with fewer seeds (0: none)")
    parser.add_argument("--sweep-count", type=int, default=None, help="N of the eps sweep")
    parser.add_argument("--sweep-eps", default=None, help="eps values of the sweep, comma-separated")
    parser.add_argument("--out", default=None)
    parser.add_argument("--replot", action="store_true", help="only rewrite table.md and the figure from results.json")
    args = parser.parse_args()
    quick = args.quick
    counts = [int(v) for v in (args.counts or ("125,250,500" if quick else "125,250,500,1000,2000,4000")).split(",")]
    extra_count = args.extra_count if args.extra_count is not None else (0 if quick else 8000)
    sweep_count = args.sweep_count or (250 if quick else 1000)
    sweep_eps = [float(v) for v in (args.sweep_eps or ("0.2,0.1" if quick else "0.4,0.2,0.1,0.05,0.025,0.0125")).split(",")]
    out = args.out or ("benchmarks/results/fpf_gain_accuracy" + ("/quick" if quick else ""))
    os.makedirs(out, exist_ok=True)
    if args.replot:
        results = json.load(open(os.path.join(out, "results.json")))
        _write(out, results)
        _plot(out, results)
        return

    start_all = time.perf_counter()
    exact = {case: ExactGain(case) for case in CASES}
    study = Study(exact)
    results = {
        "description": __doc__.split("\n\n")[2].strip(),
        "quick": quick,
        "device": str(jax.devices()[0]),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "library": _library_version(),
        "settings": {"tolerance": TOLERANCE, "max_iterations": MAX_ITERATIONS, "key": KEY,
                     "bimodal": {"means": [-BIMODAL_MEAN, BIMODAL_MEAN], "std": BIMODAL_STD},
                     "seeds": {str(n): seeds_for(n, quick) for n in counts + ([extra_count] if extra_count else [])}},
        "exact_gain_check": {
            "gaussian_quadrature_max_abs_deviation_from_1_for_abs_x_below_5": float(
                np.max(np.abs(exact["gaussian"].values[np.abs(exact["gaussian"].grid) < 5] - 1))),
            "bimodal_poisson_gain_1d_left_only_vs_two_sided_at_x": {
                str(v): [float(np.interp(v, exact["bimodal"].grid, exact["bimodal"].left_only)),
                         float(exact["bimodal"](np.array([v]))[0])] for v in (3.0, 4.0, 5.0, 6.0)}},
        "series": {},
    }
    limits: dict = {}

    def limit(case, eps):
        if (case, eps) not in limits:
            limits[(case, eps)] = limit_gain_error(case, eps, exact[case], num_points=801 if quick else 2001)
        return limits[(case, eps)]

    for name, (label, eps_of, series_counts) in series_definitions(counts, extra_count).items():
        start = time.perf_counter()
        entry = {"label": label, "cases": {}}
        for case in CASES:
            rows = {}
            for num in series_counts:
                eps = eps_of(num)
                row = study.summarise(case, num, eps, seeds_for(num, quick))
                row["limit"] = limit(case, eps)
                rows[str(num)] = row
                print(f"{name:11s} {case:8s} N={num:5d} eps={eps:.4f}: RMS {row['rms']['mean']:.4f} +- "
                      f"{row['rms']['stderr']:.4f} (Phi only {row['rms_phi_only']['mean']:.4f}; "
                      f"bias {row['split']['bias']:.4f}, spread {row['split']['spread']:.4f}; "
                      f"N=inf {row['limit']['rms_r']:.4f}), iterations {row['iterations_mean']:.0f} "
                      f"(max {row['iterations_max']}), converged {row['converged_fraction']:.2f}, "
                      f"{time.perf_counter() - start:.0f} s", flush=True)
            ns = [int(n) for n in rows]
            entry["cases"][case] = {
                "rows": rows,
                "slope_rms": fit_slope(ns, [rows[str(n)]["rms"]["mean"] for n in ns]),
                "slope_spread": fit_slope(ns, [rows[str(n)]["split"]["spread"] for n in ns]),
                "slope_bias": fit_slope(ns, [max(rows[str(n)]["split"]["bias"], 1e-12) for n in ns]),
            }
        entry["wall_s"] = time.perf_counter() - start
        results["series"][name] = entry
        _write(out, results)

    start = time.perf_counter()
    sweep = {"count": sweep_count, "cases": {}}
    for case in CASES:
        rows = {}
        for eps in sweep_eps:
            row = study.summarise(case, sweep_count, eps, seeds_for(sweep_count, quick))
            row["limit"] = limit(case, eps)
            rows[str(eps)] = row
            print(f"sweep {case:8s} N={sweep_count} eps={eps}: RMS {row['rms']['mean']:.4f} (bias "
                  f"{row['split']['bias']:.4f}, spread {row['split']['spread']:.4f}, N=inf "
                  f"{row['limit']['rms_r']:.4f}), iterations {row['iterations_mean']:.0f}", flush=True)
        sweep["cases"][case] = {"rows": rows, "slope_spread_vs_eps": fit_slope(
            sweep_eps, [rows[str(e)]["split"]["spread"] for e in sweep_eps])}
    sweep["wall_s"] = time.perf_counter() - start
    results["eps_sweep"] = sweep
    results["max_reimplementation_gap"] = study.max_reimplementation_gap
    results["compile_s"] = study.compile_s
    results["wall_s"] = time.perf_counter() - start_all
    _write(out, results)
    _plot(out, results)
    print(f"r formula re-implemented here vs library gain: max |difference| {study.max_reimplementation_gap:.2e}")
    print(f"total {results['wall_s']:.0f} s (compile {study.compile_s:.0f} s); wrote {out}", flush=True)


def _library_version() -> dict:
    """Commit and the hash of the kernel gain's source as run (the working tree may differ from HEAD)."""
    here = os.path.dirname(os.path.abspath(__file__))
    source = os.path.join(here, "..", "ot_filter", "continuous", "gains", "kernel.py")
    info = {"kernel_py_sha256": hashlib.sha256(open(source, "rb").read()).hexdigest()[:16]}
    try:
        info["commit"] = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True,
                                        text=True, check=True).stdout.strip()
        info["kernel_py_modified"] = bool(subprocess.run(
            ["git", "status", "--porcelain", "ot_filter/continuous/gains/kernel.py"], cwd=os.path.join(here, ".."),
            capture_output=True, text=True, check=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        pass
    return info


def _fmt(stat: dict) -> str:
    return f"{stat['mean']:.4f} ± {stat['stderr']:.4f}"


def _slope(slope: dict) -> str:
    return f"{slope['slope']:+.2f} ± {slope['stderr']:.2f}" if np.isfinite(slope["stderr"]) else f"{slope['slope']:+.2f}"


def _write(out: str, results: dict) -> None:
    write_text_atomic(os.path.join(out, "results.json"), json.dumps(results, indent=1))
    series = results["series"]
    lines = ["# Kernel (diffusion-map) FPF gain: error vs particle count N (1-D, h(x) = x)", "",
             "RMS over the particles of K_N(X^i) - K(X^i), mean ± s.e. over seeds "
             f"({', '.join(f'N={n}: {s}' for n, s in results['settings']['seeds'].items())} seeds); "
             f"fixed point to tolerance {results['settings']['tolerance']:g} (max "
             f"{results['settings']['max_iterations']} iterations); float64, {results['device']}."
             + (" QUICK SETTINGS." if results["quick"] else ""), ""]
    for case in CASES:
        names = [n for n in series if case in series[n]["cases"]]
        if not names:
            continue
        counts = sorted({int(c) for n in names for c in series[n]["cases"][case]["rows"]})
        lines += [f"## {case}", "", "| N | " + " | ".join(series[n]["label"] for n in names) + " |",
                  "|--:|" + "--:|" * len(names)]
        for num in counts:
            cells = []
            for n in names:
                row = series[n]["cases"][case]["rows"].get(str(num))
                cells.append("" if row is None else _fmt(row["rms"]) + (f" (eps {row['eps']:.3f})" if "N^" in n else ""))
            lines.append(f"| {num} | " + " | ".join(cells) + " |")
        lines.append("| N = ∞ limit (eps-bias), at the largest N's eps | " + " | ".join(
            f"{series[n]['cases'][case]['rows'][str(max(int(c) for c in series[n]['cases'][case]['rows']))]['limit']['rms_r']:.4f}"
            for n in names) + " |")
        lines.append("| slope of log RMS vs log N | " + " | ".join(_slope(series[n]["cases"][case]["slope_rms"]) for n in names) + " |")
        lines.append("| slope of the spread | " + " | ".join(_slope(series[n]["cases"][case]["slope_spread"]) for n in names) + " |")
        lines += [""]
    lines += ["Rows use the seeds whose fixed point converged within "
              f"{results['settings']['max_iterations']} iterations; the others (the library then returns the "
              "constant gain) are counted under fallbacks below.", "",
              "## Bias / spread split (errors of all seeds pooled, binned by x; bias² + spread² ≈ MSE)", "",
              "| case | series | N | eps | RMS | median RMS | max abs error | bias | spread | N = ∞ bias | iterations mean (max) | converged "
              f"| over the default cap ({DEFAULT_MAX_ITERATIONS}) "
              "| fallbacks: RMS as delivered |",
              "|--|--|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
    for case in CASES:
        for n in series:
            for num, row in series[n]["cases"].get(case, {}).get("rows", {}).items():
                lines.append(f"| {case} | {series[n]['label']} | {num} | {row['eps']:.3f} | {row['rms']['mean']:.4f} | "
                             f"{row['rms_median']:.4f} | {row['max_abs_error']:.2f} | "
                             f"{row['split']['bias']:.4f} | {row['split']['spread']:.4f} | {row['limit']['rms_r']:.4f} | "
                             f"{row['iterations_mean']:.0f} ({row['iterations_max']}) | {row['converged_fraction']:.2f} | "
                             f"{row['over_default_cap']} | {row['fallbacks']}: {row['rms_as_delivered']['mean']:.4f} |")
    lines += ["", "## Gain formula: r = Phi + eps h (library) vs Phi alone (notes), same fixed point", "",
              "| case | series | N | eps | RMS with r | RMS with Phi | N = ∞: r | N = ∞: Phi |",
              "|--|--|--:|--:|--:|--:|--:|--:|"]
    for case in CASES:
        for n in series:
            for num, row in series[n]["cases"].get(case, {}).get("rows", {}).items():
                lines.append(f"| {case} | {series[n]['label']} | {num} | {row['eps']:.3f} | {_fmt(row['rms'])} | "
                             f"{_fmt(row['rms_phi_only'])} | {row['limit']['rms_r']:.4f} | {row['limit']['rms_phi']:.4f} |")
    if "eps_sweep" in results:
        sweep = results["eps_sweep"]
        lines += ["", f"## eps sweep at N = {sweep['count']}", "",
                  "| case | eps | RMS | bias | spread | N = ∞ bias | RMS with Phi only | iterations mean (max) |",
                  "|--|--:|--:|--:|--:|--:|--:|--:|"]
        for case, entry in sweep["cases"].items():
            for eps, row in entry["rows"].items():
                lines.append(f"| {case} | {eps} | {_fmt(row['rms'])} | {row['split']['bias']:.4f} | "
                             f"{row['split']['spread']:.4f} | {row['limit']['rms_r']:.4f} | "
                             f"{row['rms_phi_only']['mean']:.4f} | {row['iterations_mean']:.0f} ({row['iterations_max']}) |")
            lines.append(f"| {case} | slope of log spread vs log eps | {_slope(entry['slope_spread_vs_eps'])} | | | | | |")
    if "wall_s" in results:
        lines += ["", f"Runtime {results['wall_s']:.0f} s (compile {results['compile_s']:.0f} s); "
                  f"r formula re-implemented here vs the library's gain: max |difference| "
                  f"{results['max_reimplementation_gap']:.1e}; series: " + ", ".join(
                      f"{series[n]['label']} {series[n]['wall_s']:.0f} s" for n in series)
                  + f", eps sweep {results['eps_sweep']['wall_s']:.0f} s."]
    write_text_atomic(os.path.join(out, "table.md"), "\n".join(lines) + "\n")


def _log_axes(ax, ticks) -> None:
    """Log-log axes with the measured x values as the only x tick labels."""
    from matplotlib.ticker import NullFormatter

    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(ticks)
    ax.set_xticklabels([f"{t:g}" for t in ticks])
    ax.xaxis.set_minor_formatter(NullFormatter())


def _plot(out: str, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = results["series"]
    colours = dict(zip(series, ("C0", "C1", "C2", "C3")))
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    all_counts = sorted({int(c) for n in series for c in series[n]["cases"][CASES[0]]["rows"]})
    for ax, case in zip(axes, CASES):
        for n, entry in series.items():
            rows = entry["cases"][case]["rows"]
            ns = [int(c) for c in rows]
            ax.errorbar(ns, [rows[str(c)]["rms"]["mean"] for c in ns], yerr=[rows[str(c)]["rms"]["stderr"] for c in ns],
                        marker="o", color=colours[n], capsize=3,
                        label=f"{entry['label']} (slope {entry['cases'][case]['slope_rms']['slope']:+.2f})")
            ax.plot(ns, [rows[str(c)]["split"]["spread"] for c in ns], ls=":", marker=".", color=colours[n], alpha=0.7)
            if "N^" not in n:
                ax.axhline(rows[str(ns[0])]["limit"]["rms_r"], color=colours[n], ls="--", lw=1)
        anchor = series[next(iter(series))]["cases"][case]["rows"][str(all_counts[0])]["rms"]["mean"]
        grid = np.array([all_counts[0], max(int(c) for n in series for c in series[n]["cases"][case]["rows"])], float)
        for power, style in ((-0.5, (0, (1, 1))), (-0.4, (0, (5, 2))), (-0.2, (0, (3, 1, 1, 1)))):
            ax.plot(grid, 1.3 * anchor * (grid / grid[0]) ** power, color="grey", ls=style, lw=1,
                    label=f"reference slope N^{power:g}")
        _log_axes(ax, all_counts)
        ax.set_xlabel("particle count N")
        ax.set_ylabel("RMS over particles of K_N(X^i) - K(X^i)")
        ax.set_title(f"{case}: solid = RMS error (mean ± s.e.), dotted = spread,\ndashed = N = ∞ eps-bias at fixed eps")
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    ax = axes[2]
    sweep = results["eps_sweep"]
    for case, colour in zip(CASES, ("C0", "C3")):
        rows = sweep["cases"][case]["rows"]
        eps = [float(e) for e in rows]
        ax.errorbar(eps, [rows[str(e)]["rms"]["mean"] for e in eps], yerr=[rows[str(e)]["rms"]["stderr"] for e in eps],
                    marker="o", color=colour, capsize=3, label=f"{case}: RMS error")
        ax.plot(eps, [rows[str(e)]["split"]["spread"] for e in eps], ls=":", marker=".", color=colour, label=f"{case}: spread")
        ax.plot(eps, [rows[str(e)]["limit"]["rms_r"] for e in eps], ls="--", color=colour, label=f"{case}: N = ∞ eps-bias")
    _log_axes(ax, sorted(float(e) for e in sweep["cases"][CASES[0]]["rows"]))
    ax.set_xlabel("eps")
    ax.set_ylabel("RMS over particles of K_N(X^i) - K(X^i)")
    ax.set_title(f"eps sweep at N = {sweep['count']}")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    save_figure(fig, out, "gain_error_vs_particles.png")


if __name__ == "__main__":
    main()
