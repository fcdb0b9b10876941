"""Feedback particle filter (constant gain) vs the Kalman-Bucy filter on the Ornstein-Uhlenbeck model.

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false" \\
        taskset -c 0 /work/venv/bin/python benchmarks/fpf_linear_convergence.py [--quick]
        [--out benchmarks/results/fpf_linear_convergence]     (--quick: < 1 minute, to .../quick)

Model: ``continuous.ornstein_uhlenbeck()`` (dX = -X dt + dB, dY = X dt + 0.5 dW, X_0 ~ N(0, 1)).
Three references, all exact recursions (float64 throughout):

- ``kalman_bucy(dt)``: the exact Kalman filter of the Euler-Maruyama chain at step dt (library);
- the *FPF limit* at dt: the N -> infinity (mean-field) limit of ``run_fpf`` with the constant gain
  on the same grid, m' = m + A m dt + K (dY - H m dt), P' = M P M^T + B B^T dt with K = P H^T R^-1,
  M = I + A dt - K H dt / 2 (this script). It differs from ``kalman_bucy(dt)`` by O(dt) (the two
  are different consistent discretisations of the Kalman-Bucy equations), so it isolates the
  Monte-Carlo error of the FPF from its time-discretisation error;
- the continuous-time filter: ``kalman_bucy`` on a fine grid (dt_fine = 1e-4; its own O(dt_fine)
  error is estimated from a 2 dt_fine run).

Parts (one run, all measured):

1. agreement: N = 1e4, dt = 0.01, T = 500, R = 16 FPF seeds on one observation path; errors in units
   of the Monte-Carlo s.e. sqrt(P / N) (mean) and P sqrt(2 / N) (variance): RMS over time and seeds,
   and the bias (per-seed time average of the signed error, mean over seeds +- s.e.);
2. rate in N: N = 10^2 .. 10^5 (half decades), dt = 0.01, RMS error vs N, fitted log-log slope;
3. rate in dt: dt in {0.08, ..., 0.005}, N = 1e5, R seeds, horizon 5.12, against the fine-grid
   filter at the common times (multiples of the coarsest dt); fitted slope;
4. calibration of a fast unit test: the proposed test's statistics over many independent
   replicates (new path and seeds each), and its power against a 10 % gain error.

Writes results.json, table.md and convergence.png to --out.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from ot_filter import continuous as ct  # noqa: E402
from ot_filter.experiments._common import save_figure, write_text_atomic  # noqa: E402

KEY = 2026

FULL = dict(
    agreement=dict(num_particles=10_000, dt=0.01, num_steps=500, seeds=16),
    particles=dict(counts=[100, 316, 1_000, 3_162, 10_000, 31_623, 100_000], seeds=16),
    time_step=dict(dts=[0.08, 0.04, 0.02, 0.01, 0.005], dt_fine=1e-4, horizon=5.12,
                   num_particles=100_000, seeds=32),
    test=dict(num_particles=1_000, dt=0.01, num_steps=200, seeds=16, replicates=64, gain_factor=1.1),
)
QUICK = dict(
    agreement=dict(num_particles=2_000, dt=0.01, num_steps=200, seeds=8),
    particles=dict(counts=[100, 1_000, 10_000], seeds=8),
    time_step=dict(dts=[0.08, 0.04, 0.02], dt_fine=1e-4, horizon=1.28, num_particles=10_000, seeds=8),
    test=dict(num_particles=1_000, dt=0.01, num_steps=200, seeds=16, replicates=4, gain_factor=1.1),
)


# --------------------------------------------------------------------------------------------
# references


@jax.jit
def fpf_limit(parameters: ct.LinearSDEParameters, increments, dt):
    """The N -> infinity limit of ``run_fpf(..., constant_gain(), ...)`` on a linear model: the
    mean and covariance at t_1..t_T of the mean-field particle
    X' = X + A X dt + B sqrt(dt) xi + K (dY - H (X + m) / 2 dt), K = P H^T R^-1."""
    A, B, H, sigma, m0, P0 = parameters
    n = A.shape[0]
    r_inv = jnp.diag(1.0 / sigma**2)
    eye = jnp.eye(n)

    def step(carry, dy):
        mean, cov = carry
        gain = cov @ H.T @ r_inv
        mean = mean + A @ mean * dt + gain @ (dy - H @ mean * dt)
        factor = eye + A * dt - 0.5 * gain @ H * dt
        cov = factor @ cov @ factor.T + B @ B.T * dt
        cov = 0.5 * (cov + cov.T)
        return (mean, cov), (mean, cov)

    _, (means, covs) = jax.lax.scan(step, (m0, P0), increments)
    return means, covs


def _diag(cov):
    return jnp.diagonal(cov, axis1=-2, axis2=-1)


def _fpf(model, gain, increments, dt, num_particles):
    """``keys[R] -> (mean[R, T, n], variance[R, T, n])``, one compiled program per shape."""

    def run(keys):
        result = jax.vmap(lambda k: ct.run_fpf(k, model, gain, increments, dt, num_particles))(keys)
        return result.mean, result.variance

    return jax.jit(run)


def _timed(function, *args):
    start = time.perf_counter()
    output = jax.block_until_ready(function(*args))
    return jax.tree.map(np.asarray, output), time.perf_counter() - start


# --------------------------------------------------------------------------------------------
# statistics


def _normalised_errors(fpf_mean, fpf_var, ref_mean, ref_var, num_particles):
    """Errors [R, T, n] in units of the Monte-Carlo s.e. of an N-sample mean / variance."""
    se_mean = np.sqrt(ref_var / num_particles)
    se_var = ref_var * np.sqrt(2.0 / num_particles)
    return (fpf_mean - ref_mean) / se_mean, (fpf_var - ref_var) / se_var


def _z_summary(z):
    """z [R, T, n] (error / nominal s.e.): RMS over everything, and the bias = per-seed time
    average of the signed z, mean over seeds +- s.e. (seeds are independent, so the s.e. from
    their spread is valid whatever the correlation in time); t = bias / s.e."""
    per_seed_bias = z.mean(axis=(1, 2))
    per_seed_ms = (z**2).mean(axis=(1, 2))
    seeds = z.shape[0]
    bias = per_seed_bias.mean()
    bias_se = per_seed_bias.std(ddof=1) / np.sqrt(seeds)
    rms = np.sqrt(per_seed_ms.mean())
    rms_se = per_seed_ms.std(ddof=1) / np.sqrt(seeds) / (2 * rms)
    # the seed-averaged error over time, in units of its own empirical s.e. at each time
    pointwise_t = z.mean(axis=0) / (z.std(axis=0, ddof=1) / np.sqrt(seeds))
    return {
        "rms_z": float(rms), "rms_z_se": float(rms_se),
        "bias_z": float(bias), "bias_z_se": float(bias_se), "bias_t": float(bias / bias_se),
        "rms_pointwise_t_of_seed_mean": float(np.sqrt((pointwise_t**2).mean())),
    }


def _rms_over_seeds_and_time(error):
    """RMS of error [R, T, n] over seeds and time, with its s.e. (delta method over seeds)."""
    per_seed_ms = (error**2).mean(axis=(1, 2))
    rms = np.sqrt(per_seed_ms.mean())
    se = per_seed_ms.std(ddof=1) / np.sqrt(error.shape[0]) / (2 * rms) if error.shape[0] > 1 else 0.0
    return float(rms), float(se)


def _slope(xs, ys):
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = ys > 0
    slope, _ = np.polyfit(np.log(xs[ok]), np.log(ys[ok]), 1)
    return float(slope)


# --------------------------------------------------------------------------------------------
# parts


def run_agreement(key, model, config):
    dt, num_steps, num_particles, seeds = (config[k] for k in ("dt", "num_steps", "num_particles", "seeds"))
    path_key, fpf_key = jax.random.split(key)
    increments = ct.simulate_sde(path_key, model, dt, num_steps).increments
    kb = ct.kalman_bucy(model, increments, dt)
    limit_mean, limit_cov = fpf_limit(model.parameters, increments, dt)
    function = _fpf(model, ct.constant_gain(), increments, dt, num_particles)
    keys = jax.random.split(fpf_key, seeds)
    _, compile_and_run_s = _timed(function, keys)
    (mean, var), run_s = _timed(function, keys)
    refs = {"kalman_bucy": (np.asarray(kb.mean), np.asarray(_diag(kb.cov))),
            "fpf_limit": (np.asarray(limit_mean), np.asarray(_diag(limit_cov)))}
    out = dict(config, run_s=run_s, compile_s=compile_and_run_s - run_s)
    for name, (ref_mean, ref_var) in refs.items():
        z_mean, z_var = _normalised_errors(mean, var, ref_mean, ref_var, num_particles)
        out[name] = {"mean": _z_summary(z_mean), "variance": _z_summary(z_var)}
    # the deterministic difference between the two references (the FPF's O(dt) bias vs kalman_bucy)
    kb_var = refs["kalman_bucy"][1]
    se_var = kb_var * np.sqrt(2.0 / num_particles)
    out["limit_minus_kalman_bucy"] = {
        "mean_rms": float(np.sqrt(np.mean((refs["fpf_limit"][0] - refs["kalman_bucy"][0]) ** 2))),
        "variance_final": float((refs["fpf_limit"][1] - kb_var)[-1].mean()),
        "variance_time_average": float((refs["fpf_limit"][1] - kb_var).mean()),
        "variance_time_average_in_nominal_se": float(((refs["fpf_limit"][1] - kb_var) / se_var).mean()),
        "kalman_bucy_variance_final": float(kb_var[-1].mean()),
    }
    out["within_mc_error"] = {
        name: bool(all(out[name][q]["rms_z"] < 1.5 and abs(out[name][q]["bias_t"]) < 3 for q in ("mean", "variance")))
        for name in refs
    }
    return out


def run_particle_sweep(key, model, config, agreement_config):
    dt, num_steps = agreement_config["dt"], agreement_config["num_steps"]
    path_key, fpf_key = jax.random.split(key)
    increments = ct.simulate_sde(path_key, model, dt, num_steps).increments
    kb = ct.kalman_bucy(model, increments, dt)
    limit_mean, limit_cov = fpf_limit(model.parameters, increments, dt)
    refs = {"kalman_bucy": (np.asarray(kb.mean), np.asarray(_diag(kb.cov))),
            "fpf_limit": (np.asarray(limit_mean), np.asarray(_diag(limit_cov)))}
    keys = jax.random.split(fpf_key, config["seeds"])
    rows = {}
    for count in config["counts"]:
        function = _fpf(model, ct.constant_gain(), increments, dt, count)
        (mean, var), seconds = _timed(function, keys)
        row = {"seconds": seconds}
        for name, (ref_mean, ref_var) in refs.items():
            row[name] = {}
            for quantity, value, ref in (("mean", mean, ref_mean), ("variance", var, ref_var)):
                rms, se = _rms_over_seeds_and_time(value - ref)
                row[name][quantity] = {"rms": rms, "rms_se": se}
            z_mean, z_var = _normalised_errors(mean, var, ref_mean, ref_var, count)
            row[name]["mean"]["rms_z"] = _z_summary(z_mean)["rms_z"]
            row[name]["variance"]["rms_z"] = _z_summary(z_var)["rms_z"]
        rows[str(count)] = row
        print(f"  N = {count:>6}: mean RMS {row['fpf_limit']['mean']['rms']:.2e} (vs KB {row['kalman_bucy']['mean']['rms']:.2e}), "
              f"variance RMS {row['fpf_limit']['variance']['rms']:.2e} (vs KB {row['kalman_bucy']['variance']['rms']:.2e}); "
              f"{seconds:.1f} s", flush=True)
    slopes = {name: {q: _slope(config["counts"], [rows[str(c)][name][q]["rms"] for c in config["counts"]])
                     for q in ("mean", "variance")} for name in refs}
    return dict(config, dt=dt, num_steps=num_steps, results=rows, slopes=slopes, expected_slope=-0.5)


def run_time_step_sweep(key, model, config):
    dt_fine, horizon, dts = config["dt_fine"], config["horizon"], config["dts"]
    num_fine = int(round(horizon / dt_fine))
    path_key, fpf_key = jax.random.split(key)
    start = time.perf_counter()
    fine = np.asarray(ct.simulate_sde(path_key, model, dt_fine, num_fine).increments)
    kb_fine = ct.kalman_bucy(model, fine, dt_fine)
    ref_mean, ref_var = np.asarray(kb_fine.mean), np.asarray(_diag(kb_fine.cov))
    # the reference's own error: kalman_bucy at 2 dt_fine minus at dt_fine ~ the error at dt_fine
    kb_2 = ct.kalman_bucy(model, fine.reshape(num_fine // 2, 2, -1).sum(axis=1), 2 * dt_fine)
    ref_error = {"mean_rms": float(np.sqrt(np.mean((np.asarray(kb_2.mean) - ref_mean[1::2]) ** 2))),
                 "variance_rms": float(np.sqrt(np.mean((np.asarray(_diag(kb_2.cov)) - ref_var[1::2]) ** 2)))}
    reference_s = time.perf_counter() - start
    coarsest = max(dts)
    keys = jax.random.split(fpf_key, config["seeds"])
    rows = {}
    for dt in dts:
        factor = int(round(dt / dt_fine))
        stride = int(round(coarsest / dt))
        assert abs(factor * dt_fine - dt) < 1e-12 and abs(stride * dt - coarsest) < 1e-12
        coarse = jnp.asarray(fine.reshape(num_fine // factor, factor, -1).sum(axis=1))
        # common times t_j = j * coarsest, j = 1..: output index j * stride - 1 (outputs at t_1..t_T)
        idx_coarse = np.arange(stride - 1, coarse.shape[0], stride)
        idx_fine = (idx_coarse + 1) * factor - 1
        truth_mean, truth_var = ref_mean[idx_fine], ref_var[idx_fine]
        kb = ct.kalman_bucy(model, coarse, dt)
        limit_mean, limit_cov = fpf_limit(model.parameters, coarse, dt)
        function = _fpf(model, ct.constant_gain(), coarse, dt, config["num_particles"])
        (mean, var), seconds = _timed(function, keys)
        row = {"seconds": seconds, "num_steps": int(coarse.shape[0])}
        deterministic = {"kalman_bucy": (np.asarray(kb.mean), np.asarray(_diag(kb.cov))),
                         "fpf_limit": (np.asarray(limit_mean), np.asarray(_diag(limit_cov)))}
        for name, (m, v) in deterministic.items():
            row[name] = {"mean_rms": float(np.sqrt(np.mean((m[idx_coarse] - truth_mean) ** 2))),
                         "variance_rms": float(np.sqrt(np.mean((v[idx_coarse] - truth_var) ** 2)))}
        row["fpf"] = {}
        for quantity, value, truth, limit in (("mean", mean, truth_mean, deterministic["fpf_limit"][0]),
                                              ("variance", var, truth_var, deterministic["fpf_limit"][1])):
            value = value[:, idx_coarse]
            average = value.mean(axis=0)
            se = value.std(axis=0, ddof=1) / np.sqrt(value.shape[0])  # MC s.e. of the seed average
            rms = float(np.sqrt(np.mean((average - truth) ** 2)))
            mc_rms = float(np.sqrt(np.mean(se**2)))
            row["fpf"][f"{quantity}_rms"] = rms
            row["fpf"][f"{quantity}_mc_rms"] = mc_rms  # the MC part of rms^2 (in expectation)
            row["fpf"][f"{quantity}_rms_debiased"] = float(np.sqrt(max(rms**2 - mc_rms**2, 0.0)))
            # consistency: seed average vs the FPF limit at this dt, in units of its MC s.e.
            row["fpf"][f"{quantity}_vs_limit_rms_t"] = float(
                np.sqrt(np.mean(((average - limit[idx_coarse]) / se) ** 2)))
        rows[str(dt)] = row
        print(f"  dt = {dt:<6}: FPF mean {row['fpf']['mean_rms']:.2e} (MC {row['fpf']['mean_mc_rms']:.1e}), "
              f"variance {row['fpf']['variance_rms']:.2e} (MC {row['fpf']['variance_mc_rms']:.1e}); "
              f"FPF limit {row['fpf_limit']['mean_rms']:.2e} / {row['fpf_limit']['variance_rms']:.2e}; "
              f"kalman_bucy {row['kalman_bucy']['mean_rms']:.2e} / {row['kalman_bucy']['variance_rms']:.2e}; "
              f"{seconds:.1f} s", flush=True)
    slopes = {}
    for name, keys_ in (("fpf", ("mean_rms_debiased", "variance_rms_debiased")),
                        ("fpf_raw", ("mean_rms", "variance_rms")),
                        ("fpf_limit", ("mean_rms", "variance_rms")),
                        ("kalman_bucy", ("mean_rms", "variance_rms"))):
        source = "fpf" if name.startswith("fpf") and name != "fpf_limit" else name
        slopes[name] = {q: _slope(dts, [rows[str(dt)][source][k] for dt in dts])
                        for q, k in zip(("mean", "variance"), keys_)}
    return dict(config, num_common_times=int(round(horizon / coarsest)), reference_error=ref_error,
                reference_s=reference_s, results=rows, slopes=slopes, expected_slope=1.0)


def _scaled_constant_gain(factor):
    """The constant gain times ``factor`` (a deliberately wrong gain, for the test's power)."""
    base = ct.constant_gain()

    def apply(key, state, particles, h_values):
        output, state, info = base.apply(key, state, particles, h_values)
        return output._replace(gain=factor * output.gain), state, info

    return ct.Gain(base.init, apply)


def _test_statistics(z_mean, z_var):
    """The proposed test's statistics for one replicate (z [R, T, n] vs a reference)."""
    out = {}
    for quantity, z in (("mean", z_mean), ("variance", z_var)):
        s = _z_summary(z)
        out[f"{quantity}_bias_t"] = s["bias_t"]
        out[f"{quantity}_rms_z"] = s["rms_z"]
    return out


def run_test_calibration(key, model, config):
    """The proposed unit test (N, T, R seeds on one path) repeated over independent replicates."""
    dt, num_steps, count, seeds, replicates = (config[k] for k in ("dt", "num_steps", "num_particles", "seeds", "replicates"))
    params = model.parameters

    def one_replicate(replicate_key, gain):
        path_key, fpf_key = jax.random.split(replicate_key)
        increments = ct.simulate_sde(path_key, model, dt, num_steps).increments
        kb = ct.kalman_bucy(model, increments, dt)
        limit_mean, limit_cov = fpf_limit(params, increments, dt)
        result = jax.vmap(lambda k: ct.run_fpf(k, model, gain, increments, dt, count))(
            jax.random.split(fpf_key, seeds))
        return result.mean, result.variance, kb.mean, _diag(kb.cov), limit_mean, _diag(limit_cov)

    out = dict(config)
    replicate_keys = jax.random.split(key, replicates)
    # the time one test takes here (compile + run of one replicate, one core)
    start = time.perf_counter()
    jax.block_until_ready(jax.jit(lambda k: one_replicate(k, ct.constant_gain()))(replicate_keys[0]))
    out["one_test_compile_and_run_s"] = time.perf_counter() - start
    for label, gain in (("constant_gain", ct.constant_gain()),
                        (f"gain_x{config['gain_factor']}", _scaled_constant_gain(config["gain_factor"]))):
        outputs, seconds = _timed(jax.jit(jax.vmap(lambda k: one_replicate(k, gain))), replicate_keys)
        mean, var, kb_mean, kb_var, limit_mean, limit_var = outputs
        stats = {"kalman_bucy": [], "fpf_limit": []}
        for i in range(replicates):
            for name, (rm, rv) in (("kalman_bucy", (kb_mean[i], kb_var[i])), ("fpf_limit", (limit_mean[i], limit_var[i]))):
                stats[name].append(_test_statistics(*_normalised_errors(mean[i], var[i], rm, rv, count)))
        summary = {}
        for name, rows in stats.items():
            summary[name] = {}
            for stat in rows[0]:
                values = np.array([r[stat] for r in rows])
                summary[name][stat] = {"mean": float(values.mean()), "std": float(values.std(ddof=1)),
                                       "min": float(values.min()), "max": float(values.max())}
        summary["seconds"] = seconds
        out[label] = summary
    return out


# --------------------------------------------------------------------------------------------
# output


def _print_agreement(a):
    print(f"agreement (N = {a['num_particles']}, dt = {a['dt']}, T = {a['num_steps']}, R = {a['seeds']}; "
          f"run {a['run_s']:.1f} s, compile {a['compile_s']:.1f} s):")
    for name in ("kalman_bucy", "fpf_limit"):
        for q in ("mean", "variance"):
            s = a[name][q]
            print(f"  vs {name:<11} {q:<8}: RMS {s['rms_z']:.3f} +- {s['rms_z_se']:.3f} s.e., "
                  f"bias {s['bias_z']:+.3f} +- {s['bias_z_se']:.3f} s.e. (t = {s['bias_t']:+.2f})")
        print(f"  within MC error vs {name}: {a['within_mc_error'][name]}")
    d = a["limit_minus_kalman_bucy"]
    print(f"  FPF limit - kalman_bucy: variance {d['variance_time_average']:+.2e} on average "
          f"({d['variance_time_average_in_nominal_se']:+.3f} s.e. of one seed), mean RMS {d['mean_rms']:.2e}", flush=True)


def _table(results):
    lines = ["# FPF (constant gain) vs Kalman-Bucy, Ornstein-Uhlenbeck model",
             "", "dX = -X dt + dB, dY = X dt + 0.5 dW, X_0 ~ N(0, 1); float64; "
             f"device {results.get('device')}; total wall {results.get('wall_s', float('nan')):.0f} s "
             f"(process CPU {results.get('cpu_s', float('nan')):.0f} s).",
             "", "References: `kalman_bucy(dt)` = exact Kalman filter of the Euler-Maruyama chain at dt; "
             "*FPF limit* = the N -> infinity limit of the constant-gain FPF scheme at the same dt "
             "(differs from `kalman_bucy(dt)` by O(dt)); continuous = `kalman_bucy` at dt_fine."]
    if "agreement" in results:
        a = results["agreement"]
        lines += ["", f"## 1. Agreement (N = {a['num_particles']}, dt = {a['dt']}, T = {a['num_steps']}, "
                  f"R = {a['seeds']} seeds, one path)", "",
                  "Errors in units of the MC s.e. (mean: sqrt(P/N), variance: P sqrt(2/N)); RMS over time "
                  "and seeds (1 = iid-sample MC error); bias = per-seed time average of the signed error, "
                  "mean +- s.e. over seeds, t = bias / s.e.", "",
                  "| reference | quantity | RMS error (s.e.) | bias (s.e.) | bias t | within MC error |",
                  "|--|--|--:|--:|--:|--|"]
        for name in ("kalman_bucy", "fpf_limit"):
            for q in ("mean", "variance"):
                s = a[name][q]
                ok = s["rms_z"] < 1.5 and abs(s["bias_t"]) < 3
                lines.append(f"| {name} | {q} | {s['rms_z']:.3f} +- {s['rms_z_se']:.3f} | "
                             f"{s['bias_z']:+.3f} +- {s['bias_z_se']:.3f} | {s['bias_t']:+.2f} | {'yes' if ok else 'no'} |")
        d = a["limit_minus_kalman_bucy"]
        lines += ["", f"Within MC error = RMS < 1.5 s.e. and |bias t| < 3. FPF limit - kalman_bucy (deterministic, "
                  f"O(dt)): variance {d['variance_time_average']:+.2e} on average over time "
                  f"({d['variance_time_average_in_nominal_se']:+.3f} s.e. of one seed; kalman_bucy's final variance "
                  f"{d['kalman_bucy_variance_final']:.4f}), mean RMS {d['mean_rms']:.2e}. "
                  f"FPF run {a['run_s']:.1f} s for {a['seeds']} seeds."]
    if "particles" in results:
        p = results["particles"]
        lines += ["", f"## 2. Rate in N (dt = {p['dt']}, T = {p['num_steps']}, R = {p['seeds']}; RMS over time and seeds)", "",
                  "| N | mean vs FPF limit | mean vs kalman_bucy | variance vs FPF limit | variance vs kalman_bucy | "
                  "mean RMS (s.e.) | variance RMS (s.e.) | s |", "|--:|--:|--:|--:|--:|--:|--:|--:|"]
        for count in p["counts"]:
            r = p["results"][str(count)]
            cell = lambda name, q: f"{r[name][q]['rms']:.2e} +- {r[name][q]['rms_se']:.1e}"  # noqa: E731
            lines.append(f"| {count} | {cell('fpf_limit', 'mean')} | {cell('kalman_bucy', 'mean')} | "
                         f"{cell('fpf_limit', 'variance')} | {cell('kalman_bucy', 'variance')} | "
                         f"{r['fpf_limit']['mean']['rms_z']:.2f} | {r['fpf_limit']['variance']['rms_z']:.2f} | "
                         f"{r['seconds']:.1f} |")
        s = p["slopes"]
        lines += ["", f"Fitted log-log slopes (expected -1/2): vs FPF limit: mean {s['fpf_limit']['mean']:+.3f}, "
                  f"variance {s['fpf_limit']['variance']:+.3f}; vs kalman_bucy: mean {s['kalman_bucy']['mean']:+.3f}, "
                  f"variance {s['kalman_bucy']['variance']:+.3f}. (RMS in s.e. units: vs the FPF limit.)"]
    if "time_step" in results:
        t = results["time_step"]
        lines += ["", f"## 3. Rate in dt (N = {t['num_particles']}, R = {t['seeds']}, horizon {t['horizon']}, "
                  f"vs kalman_bucy at dt_fine = {t['dt_fine']}, {t['num_common_times']} common times)", "",
                  "RMS over the common times of the error against the fine-grid (continuous) filter. FPF: the "
                  "seed average; MC = RMS of its s.e. (the MC part of the RMS); debiased = sqrt(RMS^2 - MC^2); "
                  "t vs limit = RMS over times of (seed average - FPF limit) / s.e.", "",
                  "| dt | FPF mean | MC | debiased | FPF limit mean | kalman_bucy mean | FPF variance | MC | debiased | "
                  "FPF limit variance | kalman_bucy variance | t vs limit (mean / var) | s |",
                  "|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
        for dt in t["dts"]:
            r = t["results"][str(dt)]
            f = r["fpf"]
            lines.append(f"| {dt} | {f['mean_rms']:.2e} | {f['mean_mc_rms']:.1e} | {f['mean_rms_debiased']:.2e} | "
                         f"{r['fpf_limit']['mean_rms']:.2e} | {r['kalman_bucy']['mean_rms']:.2e} | "
                         f"{f['variance_rms']:.2e} | {f['variance_mc_rms']:.1e} | {f['variance_rms_debiased']:.2e} | "
                         f"{r['fpf_limit']['variance_rms']:.2e} | {r['kalman_bucy']['variance_rms']:.2e} | "
                         f"{f['mean_vs_limit_rms_t']:.2f} / {f['variance_vs_limit_rms_t']:.2f} | {r['seconds']:.1f} |")
        s = t["slopes"]
        e = t["reference_error"]
        lines += ["", "Fitted log-log slopes (expected 1): " + "; ".join(
            f"{name}: mean {s[name]['mean']:.3f}, variance {s[name]['variance']:.3f}"
            for name in ("fpf", "fpf_raw", "fpf_limit", "kalman_bucy")) + " (fpf = debiased, fpf_raw = raw RMS).",
            "", f"Reference error (kalman_bucy at 2 dt_fine minus at dt_fine, ~ its O(dt_fine) error): "
            f"mean {e['mean_rms']:.1e}, variance {e['variance_rms']:.1e}."]
    if "test" in results:
        c = results["test"]
        lines += ["", f"## 4. Unit-test calibration (N = {c['num_particles']}, dt = {c['dt']}, T = {c['num_steps']}, "
                  f"R = {c['seeds']} seeds; {c['replicates']} independent replicates)", "",
                  "Statistics per replicate (bias t = seed-mean / seed-s.e. of the per-seed time-averaged z; RMS z "
                  "over seeds and time); mean, std, min, max over replicates.", "",
                  "| FPF gain | reference | statistic | mean | std | min | max |", "|--|--|--|--:|--:|--:|--:|"]
        for label in [k for k in c if k.startswith(("constant_gain", "gain_x"))]:
            for name in ("fpf_limit", "kalman_bucy"):
                for stat, v in c[label][name].items():
                    lines.append(f"| {label} | {name} | {stat} | {v['mean']:+.3f} | {v['std']:.3f} | "
                                 f"{v['min']:+.3f} | {v['max']:+.3f} |")
        lines += ["", f"One replicate (the test body: simulate, kalman_bucy, FPF limit, {c['seeds']} vmapped FPF runs) "
                  f"compiles and runs in {c['one_test_compile_and_run_s']:.1f} s on one core."]
    return "\n".join(lines) + "\n"


def _plot(results, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(12.0, 4.6))
    colours = {"mean": "tab:blue", "variance": "tab:red"}
    if "particles" in results:
        p = results["particles"]
        counts = np.asarray(p["counts"], float)
        for q in ("mean", "variance"):
            for name, style, label in (("fpf_limit", "-o", "vs FPF limit"), ("kalman_bucy", ":x", "vs kalman_bucy(dt)")):
                ys = [p["results"][str(c)][name][q]["rms"] for c in p["counts"]]
                err = [p["results"][str(c)][name][q]["rms_se"] for c in p["counts"]]
                left.errorbar(counts, ys, yerr=err, fmt=style, color=colours[q], capsize=2,
                              label=f"{q}, {label} (slope {p['slopes'][name][q]:+.2f})")
        y0 = p["results"][str(p["counts"][0])]["fpf_limit"]["mean"]["rms"]
        left.plot(counts, y0 * (counts / counts[0]) ** -0.5, "k--", lw=1, label="slope -1/2")
        left.set(xscale="log", yscale="log", xlabel="number of particles N",
                 ylabel="RMS error over time and seeds",
                 title=f"FPF error vs N (dt = {p['dt']}, T = {p['num_steps']}, {p['seeds']} seeds)")
        left.set_xticks(counts, [f"{c:g}" for c in p["counts"]])
        left.tick_params(axis="x", which="minor", bottom=False, labelbottom=False)
        left.legend(fontsize=7)
    if "time_step" in results:
        t = results["time_step"]
        dts = np.asarray(t["dts"], float)
        for q in ("mean", "variance"):
            r = [t["results"][str(dt)] for dt in t["dts"]]
            right.errorbar(dts, [x["fpf"][f"{q}_rms_debiased"] for x in r], yerr=[x["fpf"][f"{q}_mc_rms"] for x in r],
                           fmt="-o", color=colours[q], capsize=2,
                           label=f"{q}, FPF N = {t['num_particles']:.0e} (slope {t['slopes']['fpf'][q]:.2f})")
            right.plot(dts, [x["fpf_limit"][f"{q}_rms"] for x in r], "--", color=colours[q],
                       label=f"{q}, FPF limit N = inf (slope {t['slopes']['fpf_limit'][q]:.2f})")
            right.plot(dts, [x["kalman_bucy"][f"{q}_rms"] for x in r], ":s", color=colours[q], mfc="none",
                       label=f"{q}, kalman_bucy(dt) (slope {t['slopes']['kalman_bucy'][q]:.2f})")
        y0 = t["results"][str(t["dts"][-1])]["fpf_limit"]["variance_rms"]
        right.plot(dts, y0 * dts / dts[-1], "k--", lw=1, label="slope 1")
        right.set(xscale="log", yscale="log", xlabel="time step dt",
                  ylabel="RMS error vs continuous filter (common times)",
                  title=f"Error vs dt (reference: kalman_bucy at dt = {t['dt_fine']:g})")
        right.set_xticks(dts, [f"{d:g}" for d in t["dts"]])
        right.tick_params(axis="x", which="minor", bottom=False, labelbottom=False)
        right.legend(fontsize=7)
    return save_figure(fig, out, "convergence.png")


def _write(out, results):
    write_text_atomic(os.path.join(out, "results.json"), json.dumps(results, indent=1))
    write_text_atomic(os.path.join(out, "table.md"), _table(results))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (< 1 minute), for a smoke test")
    parser.add_argument("--out", default=None,
                        help="default benchmarks/results/fpf_linear_convergence (with --quick: its quick/ subfolder)")
    args = parser.parse_args()
    config = QUICK if args.quick else FULL
    if args.out is None:
        args.out = "benchmarks/results/fpf_linear_convergence" + ("/quick" if args.quick else "")
    os.makedirs(args.out, exist_ok=True)
    model = ct.ornstein_uhlenbeck()
    results = {"device": str(jax.devices()[0]), "quick": args.quick, "x64": True,
               "xla_flags": os.environ.get("XLA_FLAGS", ""), "model": "ornstein_uhlenbeck()"}
    keys = dict(zip(("agreement", "particles", "time_step", "test"), jax.random.split(jax.random.key(KEY), 4)))
    total, total_cpu = time.perf_counter(), time.process_time()

    start = time.perf_counter()
    results["agreement"] = run_agreement(keys["agreement"], model, config["agreement"])
    results["agreement"]["wall_s"] = time.perf_counter() - start
    _print_agreement(results["agreement"])
    _write(args.out, results)

    print(f"rate in N (dt = {config['agreement']['dt']}):", flush=True)
    start = time.perf_counter()
    results["particles"] = run_particle_sweep(keys["particles"], model, config["particles"], config["agreement"])
    results["particles"]["wall_s"] = time.perf_counter() - start
    s = results["particles"]["slopes"]
    print(f"  slopes (expected -0.5): vs FPF limit mean {s['fpf_limit']['mean']:+.3f}, variance "
          f"{s['fpf_limit']['variance']:+.3f}; vs kalman_bucy mean {s['kalman_bucy']['mean']:+.3f}, "
          f"variance {s['kalman_bucy']['variance']:+.3f}; wall {results['particles']['wall_s']:.0f} s", flush=True)
    _write(args.out, results)

    print(f"rate in dt (N = {config['time_step']['num_particles']}, reference dt = {config['time_step']['dt_fine']}):",
          flush=True)
    start = time.perf_counter()
    results["time_step"] = run_time_step_sweep(keys["time_step"], model, config["time_step"])
    results["time_step"]["wall_s"] = time.perf_counter() - start
    s = results["time_step"]["slopes"]
    print("  slopes (expected 1): " + "; ".join(f"{n} mean {s[n]['mean']:.3f} variance {s[n]['variance']:.3f}" for n in s)
          + f"; reference error {results['time_step']['reference_error']}; wall {results['time_step']['wall_s']:.0f} s",
          flush=True)
    _write(args.out, results)

    print("unit-test calibration:", flush=True)
    start = time.perf_counter()
    results["test"] = run_test_calibration(keys["test"], model, config["test"])
    results["test"]["wall_s"] = time.perf_counter() - start
    for label in [k for k in results["test"] if k.startswith(("constant_gain", "gain_x"))]:
        for name in ("fpf_limit", "kalman_bucy"):
            print(f"  {label} vs {name}: " + ", ".join(
                f"{stat} {v['mean']:+.2f} +- {v['std']:.2f} [{v['min']:+.2f}, {v['max']:+.2f}]"
                for stat, v in results["test"][label][name].items()), flush=True)
    print(f"  one test: {results['test']['one_test_compile_and_run_s']:.1f} s; wall {results['test']['wall_s']:.0f} s")

    results["wall_s"] = time.perf_counter() - total
    results["cpu_s"] = time.process_time() - total_cpu  # wall > cpu: the core was shared
    _write(args.out, results)
    print(f"figure: {_plot(results, args.out)}; total wall {results['wall_s']:.0f} s, "
          f"process CPU {results['cpu_s']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
