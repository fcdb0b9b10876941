"""Prototype (2026-12-07): a conditional flow-matching Bayes update on the chapter's static example.

    PYTHONPATH=. python benchmarks/results/flow_matching/prototype.py TAG '{json}' 2,10

Regression instead of a max-min: pairs (X0, X1, Y) with X0 a smoothed prior draw independent of
(X1, Y), X1 a smoothed prior draw and Y ~ p(y | X1) simulated afresh; v(x_t, t, y) fits X1 - X0
at x_t = (1 - t) X0 + t X1. Conditioned on Y the path carries p(x) to p(x | y), so integrating
dx/dt = v(x, t, y*) from the prior particles gives posterior particles (a deterministic map).
Scored like static_keys.py: W1 per coordinate to the exact posterior over the N-sample floor,
the README table's two prior samples (key 2026).
"""
import os, sys, json, time
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax, jax.numpy as jnp, optax
import flax.linen as nn
from ot_filter import metrics
from ot_filter.models import squared_observation
from ot_filter.reference import squared_observation_posterior
from ot_filter.transport.standardisation import (smoothing_bandwidth, correlation_cholesky, smoothed_draw)

NOISE, N = 0.4, 1000

class Velocity(nn.Module):
    width: int
    depth: int
    @nn.compact
    def __call__(self, x, t, y):
        freqs = jnp.arange(1, 5, dtype=x.dtype) * jnp.pi
        temb = jnp.concatenate([t[:, None], jnp.sin(freqs * t[:, None]), jnp.cos(freqs * t[:, None])], -1)
        h = jnp.concatenate([x, y, temb], -1)
        for _ in range(self.depth):
            h = nn.silu(nn.Dense(self.width)(h))
        return nn.Dense(x.shape[-1], kernel_init=nn.initializers.zeros)(h)

def build(dim, o):
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=0.5, static=True)
    exact = squared_observation_posterior(1.0, NOISE, scale=0.5)
    net = Velocity(o.get("width", 128), o.get("depth", 3))
    iters, batch, steps = o.get("iters", 10000), o.get("batch", 1024), o.get("steps", 32)
    lr = o.get("lr", 1e-3)
    sched = optax.cosine_decay_schedule(lr, iters) if o.get("cosine", True) else lr
    opt = optax.adam(sched)
    y_obs = jnp.ones(dim)

    def update(key, prior):
        k_obs, k_init, k_train = jax.random.split(key, 3)
        mean, std = prior.mean(0), prior.std(0)
        xs = (prior - mean) / std
        ysim = jax.vmap(model.sample_observation)(jax.random.split(k_obs, N), prior)
        ymean, ystd = ysim.mean(0), ysim.std(0)
        h = smoothing_bandwidth(o.get("smoothing", 1.5), N, dim, xs.dtype)
        L = correlation_cholesky(xs)
        params = net.init(k_init, xs[:2], jnp.zeros(2), jnp.zeros((2, dim)))
        state = opt.init(params)
        def loss_fn(p, x0, x1, y, t):
            xt = (1 - t)[:, None] * x0 + t[:, None] * x1
            return jnp.mean(jnp.sum((net.apply(p, xt, t, y) - (x1 - x0)) ** 2, -1))
        def step(carry, k):
            p, s = carry
            k0, k1, kj0, kj1, ky, kt = jax.random.split(k, 6)
            x0 = smoothed_draw(kj0, xs[jax.random.randint(k0, (batch,), 0, N)], h, L)
            x1 = smoothed_draw(kj1, xs[jax.random.randint(k1, (batch,), 0, N)], h, L)
            y = jax.vmap(model.sample_observation)(jax.random.split(ky, batch), x1 * std + mean)
            y = (y - ymean) / ystd
            t = jax.random.uniform(kt, (batch,))
            l, g = jax.value_and_grad(loss_fn)(p, x0, x1, y, t)
            u, s = opt.update(g, s, p)
            return (optax.apply_updates(p, u), s), l
        (params, _), losses = jax.lax.scan(step, (params, state), jax.random.split(k_train, iters))
        yb = jnp.broadcast_to((y_obs - ymean) / ystd, (N, dim))
        dt = 1.0 / steps
        def ode(x, i):  # Heun
            t0 = jnp.full((N,), i * dt)
            v0 = net.apply(params, x, t0, yb)
            xe = x + dt * v0
            v1 = net.apply(params, xe, t0 + dt, yb)
            return x + 0.5 * dt * (v0 + v1), None
        x, _ = jax.lax.scan(ode, xs, jnp.arange(steps))
        return x * std + mean, losses

    @jax.jit
    def run(seed_key, place, grid, masses):
        prior_key, update_key, _, floor_key, compare_key = jax.random.split(seed_key, 5)
        prior = jax.vmap(model.sample_initial)(jax.random.split(prior_key, N))
        post, losses = update(jax.random.fold_in(update_key, place), prior)
        w1 = lambda s: metrics.compare_to_product_grid(compare_key, s, None, grid, masses, N).w1
        return w1(post), w1(metrics.product_grid_sample(floor_key, grid, masses, N)), losses[-200:].mean()
    grid = jnp.asarray(exact.grid)
    masses = jnp.broadcast_to(jnp.asarray(exact.density), (dim,) + exact.density.shape)
    return lambda k, p: run(k, p, grid, masses)

tag = sys.argv[1]; o = json.loads(sys.argv[2]); dims = [int(d) for d in sys.argv[3].split(",")]
keys = int(sys.argv[4]) if len(sys.argv) > 4 else 1
for dim in dims:
    run = build(dim, o)
    seeds = jax.random.split(jax.random.key(int(os.environ.get("PRIOR_KEY", "2026"))), 2)
    for place in range(keys):
        t = time.perf_counter(); vals = []
        for s in range(2):
            w1, fl, loss = jax.block_until_ready(run(seeds[s], place))
            vals.append((float(w1.mean()), float(fl.mean()), float(w1.max()), float(loss)))
        w = sum(v[0] for v in vals) / 2; f = sum(v[1] for v in vals) / 2
        print(json.dumps({"tag": tag, "dim": dim, "key": place, "w1": w, "floor": f, "ratio": w / f,
                          "worst": max(v[2] for v in vals), "loss": vals[0][3], "s": round(time.perf_counter() - t, 1)}), flush=True)
