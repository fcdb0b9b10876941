"""Does reweighting the global OT update's output by importance weights take its error at n = 10
down to the floor? (issue 17: the global ``ot()`` at most twice the floor at n = 10; measured, not
built: it does not.)

    PYTHONPATH=.:benchmarks python benchmarks/ot_importance_correction.py [--dim 10] [--seeds 2]
        [--options '{}'] [--out FILE.json]

Static example (lambda_w = 0.4, y = 1, N = 1000), the prior samples of
``benchmarks/ot_sample_size.py`` (key 2026). The trained map T moves each prior particle x_i to
z_i = T(x_i); if T is invertible, z_i is a draw from a proposal whose density is p(x_i) / |det
dT/dx (x_i)|, and the weights w_i ∝ l(y | z_i) p(z_i) |det dT/dx (x_i)| / p(x_i) make the
particles a sample of the posterior whatever T's error (the OT map as an importance sampler's
proposal). p is the prior's density: the exact N(0, I) ("oracle", which no filter knows) or a
Gaussian kernel estimate from the N particles (bandwidth Silverman's times 1 or 1.5, capped at 0.9,
on the particles standardised; at the particles themselves each one's own kernel left out), as a
filter would have to use. Where det dT/dx <= 0 T folds, the one-preimage density above does not
hold, and the particle gets weight 0 (a bias, counted in ``folded_share``). Reported per seed:
W1 per coordinate to the exact posterior (mean and worst coordinate) of the update's own output,
of the weighted particles and of N particles resampled from them, the effective sample size, the
folded share, whether the update fell back to the EnKF (then its output is not T's), and the
N-sample floor.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ot_filter as otf  # noqa: E402
from ot_filter import metrics  # noqa: E402
from ot_filter.experiments._common import write_text_atomic  # noqa: E402
from ot_filter.models import squared_observation  # noqa: E402
from ot_filter.reference import squared_observation_posterior  # noqa: E402
from ot_sample_size import NOISE, OBSERVATION, SCALE, draws, exact_scoring  # noqa: E402


def log_kde(points, centres, bandwidth, leave_out_own=False):
    """Log of an isotropic Gaussian kernel estimate at ``points`` (up to a constant);
    ``leave_out_own``: point i is centre i, whose own kernel is left out (at n = 10 it would
    outweigh the other N - 1)."""
    squared = jnp.sum((points[:, None, :] - centres[None, :, :]) ** 2, -1)
    if leave_out_own:
        squared = jnp.where(jnp.eye(points.shape[0], dtype=bool), jnp.inf, squared)
    return jax.scipy.special.logsumexp(-0.5 * squared / bandwidth**2, axis=1)


def build(dim: int, options: dict, num_particles: int = 1000):
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=SCALE, static=True)
    update = otf.ot(**options)
    w1, exact_samples = exact_scoring(dim)
    exact = squared_observation_posterior(OBSERVATION, NOISE, scale=SCALE)
    grid = jnp.asarray(exact.grid)
    cdf = jnp.cumsum(exact.density) / jnp.sum(exact.density)
    y = jnp.full((dim,), OBSERVATION)

    def log_likelihood(x):
        return jnp.sum(-0.5 * ((y - SCALE * x * x) / NOISE) ** 2, axis=-1)

    @jax.jit
    def go(key):
        d = draws(key, model, num_particles, 10)
        state = update.init(d.init_key, d.prior, model)
        moved, state, info = update.apply(d.apply_key, state, d.prior, y, model)  # moved = T(prior) unless diverged

        def transport(x, simulated):
            return update.transport(state, x[None], y, simulated[None])[0]

        jacobians = jax.vmap(jax.jacfwd(transport))(d.prior, state.simulated_observations)
        sign, log_det = jnp.linalg.slogdet(jacobians)
        out = {"own_output": w1(moved), "floor": w1(exact_samples(d.floor_key, num_particles)),
               "folded_share": jnp.mean(sign <= 0), "diverged": info.diverged}
        silverman = (4.0 / (dim + 2)) ** (1 / (dim + 4)) * num_particles ** (-1 / (dim + 4))
        mean, std = d.prior.mean(0), d.prior.std(0)
        centres = (d.prior - mean) / std
        densities = {"oracle": (lambda x: -0.5 * jnp.sum(x * x, axis=-1),) * 2}
        for factor in (1.0, 1.5):
            bandwidth = min(factor * silverman, 0.9)
            densities[f"kde_{factor}"] = (
                (lambda h: lambda x: log_kde((x - mean) / std, centres, h))(bandwidth),
                (lambda h: lambda x: log_kde(centres, centres, h, leave_out_own=True))(bandwidth))
        for name, (log_prior, log_prior_at_particles) in densities.items():
            log_weights = log_likelihood(moved) + log_prior(moved) - log_prior_at_particles(d.prior) + log_det
            log_weights = jnp.where(sign > 0, log_weights, -jnp.inf)
            weights = jnp.exp(log_weights - jax.scipy.special.logsumexp(log_weights))
            out[f"{name}_ess"] = 1.0 / jnp.sum(weights**2)
            out[f"{name}_weighted"] = jax.vmap(lambda column: metrics.wasserstein_1d(column, grid, cdf, weights),
                                               in_axes=1)(moved)
            chosen = jax.random.choice(jax.random.fold_in(key, 7), num_particles, (num_particles,), p=weights)
            out[f"{name}_resampled"] = w1(moved[chosen])
        return out

    return go


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dim", type=int, default=10)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--options", default="{}", help="ot() options as JSON")
    parser.add_argument("--out", default="benchmarks/results/ot_dimension_size_rule/importance_correction.json")
    args = parser.parse_args()
    go = build(args.dim, json.loads(args.options))
    seeds = []
    for seed, key in enumerate(jax.random.split(jax.random.key(2026), args.seeds)):
        started = time.perf_counter()
        out = jax.block_until_ready(go(key))
        record = {name: ({"mean": float(np.mean(value)), "worst": float(np.max(value))} if np.ndim(value)
                         else value.item()) for name, value in out.items()}
        record["seconds"] = round(time.perf_counter() - started, 1)
        print(json.dumps({"seed": seed, **record}), flush=True)
        seeds.append(record)
    records = json.load(open(args.out)) if os.path.exists(args.out) else []
    records.append({"dim": args.dim, "options": json.loads(args.options), "per_seed": seeds,
                    "device": str(jax.devices()[0])})
    write_text_atomic(args.out, json.dumps(records, indent=1))


if __name__ == "__main__":
    main()
