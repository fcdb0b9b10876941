"""Standard twin experiments reach the published RMSE (within 10%), in float32 as in float64.

Configurations and published analysis RMSEs are those DAPPER (v1.7) lists for
Lorenz-63 / Sakov et al. (2012) and Lorenz-96 / Sakov & Oke (2008). rmse.a is DAPPER's: the
per-analysis RMSE over components, averaged over analyses after the burn-in. We average it over
8 independent truths (one vmapped program) to keep seed luck out of a 10% comparison.

One configuration is marginal: the Lorenz-96 square-root EnKF with inflation 1.013 loses the
track in about 4% of 1,001-cycle runs, in ot_filter (32 of 768 runs, float32 and float64 alike)
and in DAPPER itself (4 of 136 runs, and 1 of the 8 in benchmarks/results/lorenz_twin.md). A
single such run dominates a mean of 8, so for that configuration we compare the median with the
published value and bound the number of divergent runs (rmse.a > 2x published) by 2 of 8
(probability about 0.3% at a 4% rate). The stable configurations are held to the mean.
"""

import jax
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.experiments.twin_configurations import TWIN_CONFIGURATIONS, TWIN_EXPERIMENTS

NUM_TRUTHS = 8
LORENZ63 = TWIN_EXPERIMENTS["lorenz63"]  # 1001 analyses, burn-in 64 (t > 16, observations every 0.25)


def twins(model, num_truths=NUM_TRUTHS, seed=0, num_analyses=LORENZ63.num_analyses):
    keys = jax.random.split(jax.random.key(seed), num_truths)
    return jax.vmap(lambda k: otf.simulate(k, model, num_analyses))(keys)


def mean_rmse(model, update, num_particles, burn_in, seed=0, data=None, average=np.mean):
    return float(average(rmse_per_truth(model, update, num_particles, burn_in, seed, data)))


def rmse_per_truth(model, update, num_particles, burn_in, seed=0, data=None, num_analyses=LORENZ63.num_analyses):
    states, observations = twins(model, seed=seed, num_analyses=num_analyses) if data is None else data
    filter_keys = jax.random.split(jax.random.key(seed + 1), states.shape[0])
    run = jax.jit(jax.vmap(
        lambda k, y: otf.run_filter(k, model, update, y, num_particles, save_every=0).mean
    ))
    rmse = otf.metrics.rmse(run(filter_keys, observations), states)[:, burn_in:].mean(axis=1)
    assert np.all(np.isfinite(rmse))
    return np.asarray(rmse, np.float64)


CASES = {name: c for name, c in TWIN_CONFIGURATIONS.items() if c.expected_rmse is not None}
MARGINAL = {"L96/EnKF-Sqrt-N24"}  # occasionally diverges (see above)
QUICK = "L63/EnKF-Sqrt-N10"  # the quick tier's twin experiment; the others are marked long
assert QUICK in CASES


@pytest.mark.parametrize("case", [c if c == QUICK else pytest.param(c, marks=pytest.mark.long) for c in sorted(CASES)])
def test_published_rmse_within_ten_percent(case):
    config = CASES[case]
    experiment, published = config.experiment, config.expected_rmse
    rmse = rmse_per_truth(experiment.make_model(), config.build_update(), config.num_particles,
                          experiment.burn_in, num_analyses=experiment.num_analyses)
    if case in MARGINAL:
        assert np.median(rmse) < 1.10 * published, (case, rmse, published)
        assert np.sum(rmse > 2 * published) <= 2, (case, rmse)
    else:
        assert rmse.mean() < 1.10 * published, (case, rmse, published)


def per_run_rmse(model, update, data, seeds=(1, 2, 3)):
    """Time-mean RMSE of every (filter seed, truth) pair: [len(seeds) * num_truths]."""
    states, observations = data
    run = jax.jit(jax.vmap(
        lambda k, y: otf.run_filter(k, model, update, y, 10, save_every=0).mean
    ))
    values = []
    for seed in seeds:
        keys = jax.random.split(jax.random.key(seed), states.shape[0])
        rmse = otf.metrics.rmse(run(keys, observations), states)[:, LORENZ63.burn_in:].mean(axis=1)
        values.append(np.asarray(rmse, np.float64))
    return np.concatenate(values)


@pytest.mark.parametrize("perturbed", [False, True], ids=["sqrt", "perturbed"])
@pytest.mark.long
def test_float32_as_accurate_as_float64(perturbed):
    """The same 32 truths (simulated in float64) filtered in both precisions, N = 10, 3 filter
    seeds each. The runs differ in their own random draws, so the mean RMSEs must agree within
    3 standard errors of their difference (measured from the 96 + 96 runs). The square-root
    filter is stable enough for a sharper check too: its medians agree within 5%. (The
    perturbed EnKF with N = 10 occasionally loses the track, in either precision, as DAPPER's
    does, so its spread is wide.)"""
    inflation = 1.02 if not perturbed else 1.04
    with jax.enable_x64(True):
        model = otf.models.lorenz63()
        states, observations = (np.asarray(a) for a in twins(model, num_truths=32, seed=7))
        update = otf.enkf(inflation, perturbed=perturbed, rotate=True)
        double = per_run_rmse(model, update, (states, observations))
    model = otf.models.lorenz63()
    update = otf.enkf(inflation, perturbed=perturbed, rotate=True)
    single = per_run_rmse(model, update, (states.astype(np.float32), observations.astype(np.float32)))
    standard_error = np.sqrt(single.var(ddof=1) / single.size + double.var(ddof=1) / double.size)
    assert abs(single.mean() - double.mean()) < 3 * standard_error, (single.mean(), double.mean())
    if not perturbed:
        assert abs(np.median(single) - np.median(double)) < 0.05 * np.median(double)
