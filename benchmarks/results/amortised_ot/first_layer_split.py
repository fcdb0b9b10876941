"""The (a) cost diagnostic of 2026-12-05 (README, "The network's pass already runs at about the
core's arithmetic rate"): T's forward pass with the first layer applied to [x; y; context] for
every particle, against the same layer split so that the shared y and context part is formed once.
Run: PYTHONPATH=. taskset -c 0 python benchmarks/results/amortised_ot/first_layer_split.py"""
import time, jax, jax.numpy as jnp
from ot_filter.transport.networks import TransportNetwork
for W, n, m in [(64, 2, 2), (32, 2, 2), (64, 3, 1)]:
    c = 4*n+2*m
    net = TransportNetwork(width=W, num_blocks=1)
    x = jax.random.normal(jax.random.key(0), (10, 1000, n)); y = jnp.ones((10, 1000, m+c))
    p = net.init(jax.random.key(1), x[0], y[0])
    p = jax.tree.map(lambda a: a + 0.01, p)
    full = jax.jit(jax.vmap(lambda x, y: net.apply(p, x, y)))
    def split1(x, yc):
        q = p['params']['_ResidualMLP_0']
        K, b = q['Dense_0']['kernel'], q['Dense_0']['bias']
        h = jax.nn.relu(x @ K[:n] + (yc @ K[n:] + b))
        r = jax.nn.relu(h @ q['Dense_1']['kernel'] + q['Dense_1']['bias'])
        r = r @ q['Dense_2']['kernel'] + q['Dense_2']['bias']
        h = jax.nn.relu(h + r)
        return x + h @ q['Dense_3']['kernel'] + q['Dense_3']['bias']
    split = jax.jit(jax.vmap(split1))
    y1 = y[:, 0]
    print(jnp.abs(full(x, y) - split(x, y1)).max())
    for name, f, a in [("full", full, (x, y)), ("split", split, (x, y1)), ("full", full, (x, y)), ("split", split, (x, y1))]:
        jax.block_until_ready(f(*a)); best = 1e9
        for _ in range(200):
            t = time.perf_counter(); jax.block_until_ready(f(*a)); best = min(best, time.perf_counter() - t)
        print(W, n, m, name, "%.3f ms per sim" % (best * 1e3 / 10))
