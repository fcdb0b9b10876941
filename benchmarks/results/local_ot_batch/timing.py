"""Record of 2026-12-07: seconds of one local_ot update after compilation at n = 2, 10, 50 for the
mini-batch sizes given (default 128,512), in one process: a one-off update (10,000 iterations)
and one filter step with the dynamic example's settings (64 iterations, width 64, f's AdamW 3e-4).

    PYTHONPATH=. taskset -c 0 python benchmarks/results/local_ot_batch/timing.py 128,256
"""
import os, sys, time, json
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax, jax.numpy as jnp, optax
import ot_filter as otf
from ot_filter.models import squared_observation

def timed(f, *a, reps=3):
    jax.block_until_ready(f(*a)); ts = []
    for _ in range(reps):
        t = time.perf_counter(); jax.block_until_ready(f(*a)); ts.append(time.perf_counter() - t)
    return min(ts)

rows = []
for dim in (2, 10, 50):
    model = squared_observation(dim=dim, noise=0.4, observation_scale=0.5, static=True)
    prior = jax.vmap(model.sample_initial)(jax.random.split(jax.random.key(0), 1000))
    y = jnp.ones(dim)
    for batch in [int(b) for b in (sys.argv[1] if len(sys.argv) > 1 else "128,512").split(",")]:
        for label, opts in (("one-off (10,000 iterations)", {}),
                            ("filter step (64 warm-started)", dict(num_iterations=64, width=64,
                                                                   potential_optimizer=optax.adamw(3e-4, weight_decay=1.0)))):
            update = otf.local_ot(otf.local_windows(model.geometry, 0.0), batch_size=batch, **opts)
            state = update.init(jax.random.key(1), prior, model)
            f = jax.jit(lambda k, s: update.apply(k, s, prior, y, model)[0])
            s = timed(f, jax.random.key(2), state, reps=1 if not opts else 5)
            rows.append({"dim": dim, "batch": batch, "case": label, "seconds": s}); print(json.dumps(rows[-1]), flush=True)
