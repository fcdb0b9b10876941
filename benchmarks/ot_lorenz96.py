"""Lorenz-96 (n = 40, N = 100): the localised OT filter against the LETKF, with linear, squared
and absolute-value observations, on the same truths.

    PYTHONPATH=. python benchmarks/ot_lorenz96.py [--operator linear|square|abs] [--simulations 4]
        [--steps 500] [--methods letkf,local_ot,...] [--noise 1.0] [--every 1]

Methods (every one on the runner's truths of ``ot-filter run lorenz96`` for the same seed):

- ``enkf``, ``letkf``, ``sir``, ``local_ot``: the catalogue's (``runner.catalogue.lorenz96_update``);
  ``local_ot`` is the localised OT filter with the deterministic layer (the LETKF's Gaspari-Cohn
  taper, windows out to its support: 29 observations), fresh networks at every step (T starts as
  the layer) trained for 64 iterations.
- ``local_ot:K``, ``local_ot:K:F``, ``local_ot:K:F:B`` or ``local_ot:K:F:B:I``: ``local_ot`` with
  K iterations a step (fresh networks at every step), f's learning rate F (default 1e-4: f moves
  little in 64 steps of it; leave it empty, ``local_ot:64::512``, to keep it), mini-batches of B
  local pairs (default 128) and the layer's inflation I (default the catalogue's 1.04); a fifth
  field ``fresh`` draws each mini-batch's local observations afresh (``fresh_observations=True``),
  e.g. ``local_ot:64::512::fresh``.
- ``local_ot_avg:K`` or ``local_ot_avg:K:I``: K trainings of the catalogue's ``local_ot`` at every
  step (each member its own keys: other fresh networks and mini-batches), the K transported
  ensembles averaged particle by particle, which is the output of the average of the K maps
  (``otf.averaged_maps``, since 0.2.18; the recorded runs used this benchmark's own loop over the
  members, which counted a step as fallen back when any member fell back and averaged all K); I: the layer's inflation. The members' training noise partly cancels: on the
  static example three trainings of the global map took a quarter off W1
  (``docs/ot_at_scale.md``). K times the cost.
- ``letkf:R:I``: the LETKF with a Gaspari-Cohn radius R and inflation I (the catalogue's: 4 and
  1.04, tuned at N = 100), to check that a comparison at another N is not won against an
  untuned LETKF.
- ``layer``: that deterministic layer alone (the network never used): the LETKF itself
  (``tests/test_local_ot.py``).
- ``letkf_step``, ``layer_step``, ``local_ot_step``: the same three with a step taper of the
  LETKF's radius (windows of 4 observations either side), the catalogue's choice before.
- ``local_ot_location``: the catalogue's ``local_ot``, its networks also reading where each window
  sits (``location_context=True``: the mean and spread of its coordinates and observations,
  which standardisation hides; with y = |x| or x^2 a window near 0 is ambiguous in sign and one
  far from 0 is not).
- ``etpf:A``, ``etpf:A:I`` or ``etpf:A:I:R``: the localised ensemble transform particle filter
  (``otf.local_etpf``: an exact 1-D transport of each coordinate to its locally weighted
  ensemble, no network) on the likelihood to the power A, then the LETKF on the rest
  (``otf.split_likelihood``; the LETPF alone when A = 1); inflation I (default the catalogue's
  1.04) of the prior anomalies, Gaspari-Cohn radius R (default 4). ``etpf_after:...``: the
  LETKF's part first (the hybrid of Chustagulprom, Reich & Reinhardt 2016). What a localised
  non-Gaussian update gains at this N without a network's training noise.
- ``letkf_split:A`` or ``letkf_split:A:I``: ``etpf_after:A:I`` with the LETKF again in place of the
  transport: what the split alone does (with a nonlinear h the second LETKF linearises around the
  first one's output, as a multiple-data-assimilation step does).
- ``local_ot_tempered:A`` (or ``local_ot_tempered:A:location``): the LETKF on the likelihood to
  the power 1 - A, then the catalogue's ``local_ot`` (inflation 1: the LETKF inflated) on the
  rest (``otf.split_likelihood``), as ``etpf_after:A`` with the neural map in place of the exact
  transport.
- ``ot_etpf:A``: the catalogue's neural ``local_ot`` (its layer inflated as the LETKF is) on the
  likelihood to the power 1 - A, then the LETPF on the rest: the hybrid ``etpf_after:A`` with the
  neural map in place of its LETKF step, so that the step that sees most of the likelihood keeps
  a non-Gaussian (e.g. bimodal) forecast. ``ot_letkf:A``: its control, the LETKF as the second
  step (what the transport adds).
- ``local_flow``, ``local_flow:F:L`` with flags ``:fresh``, ``:nofresh`` and ``:cold``: the
  localised flow (``otf.local_flow``) on the catalogue's windows and deterministic layer (the flow
  starts from each window's LETKF analysis), its velocity warm-started from step to step with F
  iterations at the first step halving to L (default the library's 2000 and 500); ``fresh`` /
  ``nofresh``: fresh observations in every mini-batch or not (default the library's: on, the
  noise being additive Gaussian); ``cold``: a fresh network and F iterations at every step.
- ``local_ot_warm``: the catalogue's windows and layer, with networks warm-started from step to
  step (the 256 -> 64 schedule), T's learning rate 1e-4 and a loss bound of 0.02 that restarts
  them when they drift.
- ``local_ot_perturbed``: the localised OT filter with the perturbed-observation layer (radius 3,
  state radius 1), the catalogue's choice before the deterministic layer.

RMSE of the filter mean over the second half of the run, mean ± standard error over the
simulations, the paired difference to the LETKF on the same truths (mean ± standard error), the
steps that fell back to the layer, and seconds (compile excluded). Writes
``ot_lorenz96_<operator>.{json,md}`` to --out (rows of earlier runs of other methods kept).
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
from ot_filter.experiments._common import diverged_flags, simulate_truths, then_etpf, write_text_atomic  # noqa: E402
from ot_filter.models import lorenz96  # noqa: E402
from ot_filter.runner.catalogue import LORENZ96_LOCAL, cell_key, lorenz96_local_ot, lorenz96_update  # noqa: E402

METHODS = ("enkf", "letkf", "letkf_step", "sir", "layer", "layer_step", "local_ot", "local_ot_step", "local_ot_location",
           "local_ot_warm", "local_ot_perturbed")


def build(method: str, model):
    local = LORENZ96_LOCAL
    radius = local["ot_taper_radius"]
    if method.startswith("letkf:"):  # letkf:R:I, a Gaspari-Cohn radius R and inflation I
        radius, inflation = (float(v) for v in method.split(":")[1:])
        return otf.letkf(otf.localisation(model.geometry, radius), inflation=inflation)
    if method.startswith("local_ot_avg:"):  # local_ot_avg:K[:I]
        count, *rest = method.split(":")[1:]
        options = {"inflation": float(rest[0])} if rest and rest[0] else {}
        return otf.averaged_maps(lorenz96_local_ot(model, local["ot_iterations"], warm_start=False, **options),
                                 int(count))
    if method.startswith("etpf:") or method.startswith("etpf_after:"):  # etpf[_after]:A[:I[:R]]
        alpha, *rest = (float(v) for v in method.split(":")[1:])
        if len(rest) > 2:
            raise ValueError(f"unknown method {method!r}: etpf[_after]:A[:I[:R]]")
        localisation = otf.localisation(model.geometry, rest[1] if len(rest) > 1 else radius)
        inflation = rest[0] if rest else local["inflation"]
        if alpha == 1.0:
            return otf.local_etpf(localisation, inflation=inflation)
        if method.startswith("etpf_after"):
            return otf.split_likelihood([otf.letkf(localisation, inflation), otf.local_etpf(localisation)],
                                        [1.0 - alpha, alpha])
        return otf.split_likelihood([otf.local_etpf(localisation, inflation), otf.letkf(localisation)],
                                    [alpha, 1.0 - alpha])
    if method.startswith("letkf_split:"):  # letkf_split:A[:I], the control of etpf_after:A[:I]
        alpha, *rest = (float(v) for v in method.split(":")[1:])
        localisation = otf.localisation(model.geometry, radius)
        return otf.split_likelihood([otf.letkf(localisation, rest[0] if rest else local["inflation"]),
                                     otf.letkf(localisation)], [1.0 - alpha, alpha])
    if method.startswith("local_ot_tempered:"):  # local_ot_tempered:A[:location]
        alpha, *rest = method.split(":")[1:]
        options = {"location_context": True} if rest == ["location"] else {}
        if rest and not options:
            raise ValueError(f"unknown method {method!r}: local_ot_tempered:A[:location]")
        return otf.split_likelihood(
            [otf.letkf(otf.localisation(model.geometry, radius), inflation=local["inflation"]),
             lorenz96_local_ot(model, local["ot_iterations"], inflation=1.0, warm_start=False, **options)],
            [1.0 - float(alpha), float(alpha)])
    if method.startswith("ot_etpf:") or method.startswith("ot_letkf:"):  # ot_etpf:A / ot_letkf:A
        fields = method.split(":")[1:]
        if len(fields) != 1:
            raise ValueError(f"unknown method {method!r}: ot_etpf:A or ot_letkf:A")
        alpha = float(fields[0])
        localisation = otf.localisation(model.geometry, local["letkf_radius"])
        first = lorenz96_local_ot(model, local["ot_iterations"], warm_start=False)
        if method.startswith("ot_etpf"):  # the runner's local_ot_etpf when A = ETPF_POWER
            return then_etpf(first, localisation, alpha)
        return otf.split_likelihood([first, otf.letkf(localisation)], [1.0 - alpha, alpha])
    if method == "letkf_step":
        return otf.letkf(otf.localisation(model.geometry, radius, taper="step"), inflation=local["inflation"])
    if method in ("layer", "layer_step"):  # a loss bound no training meets: every step is the layer alone
        return lorenz96_local_ot(model, 1, taper="step" if method == "layer_step" else "gaspari_cohn",
                                 divergence_threshold=1e-12)
    if method.startswith("local_ot:"):
        iterations, *rest = method.split(":")[1:]
        if len(rest) > 4 or (len(rest) == 4 and rest[3] not in ("", "fresh")):
            raise ValueError(f"unknown method {method!r}: local_ot:K[:F[:B[:I[:fresh]]]]")
        options = {}
        if rest and rest[0]:
            options["potential_learning_rate"] = float(rest[0])
        if len(rest) > 1 and rest[1]:
            options["batch_size"] = int(rest[1])
        if len(rest) > 2 and rest[2]:
            options["inflation"] = float(rest[2])
        if len(rest) > 3 and rest[3]:
            options["fresh_observations"] = True
        return lorenz96_local_ot(model, int(iterations), warm_start=False, **options)
    if method.startswith("local_flow"):  # local_flow[:F:L][:fresh|:nofresh][:cold]
        fields = method.split(":")[1:]
        numbers = [field for field in fields if field.isdigit()]
        flags = set(fields) - set(numbers)
        if len(numbers) not in (0, 2) or not flags <= {"fresh", "nofresh", "cold"}:
            raise ValueError(f"unknown method {method!r}: local_flow[:F:L][:fresh|:nofresh][:cold]")
        first, floor = (int(numbers[0]), int(numbers[1])) if numbers else (2_000, 500)
        fresh = True if "fresh" in flags else False if "nofresh" in flags else None
        from ot_filter.localisation import taper_support

        windows = otf.local_windows(model.geometry, taper_support(radius, "gaspari_cohn"), local["ot_state_radius"])
        cold = "cold" in flags  # a fresh network and F iterations at every step
        return otf.local_flow(windows, num_iterations=(first, first if cold else floor), enkf_layer="deterministic",
                              taper="gaspari_cohn", inflation=local["inflation"], fresh_observations=fresh,
                              warm_start=not cold)
    if method == "local_ot_step":
        return lorenz96_local_ot(model, local["ot_iterations"], taper="step", warm_start=False)
    if method == "local_ot_location":
        return lorenz96_local_ot(model, local["ot_iterations"], warm_start=False, location_context=True)
    if method == "local_ot_warm":
        return lorenz96_local_ot(model, (256, 64), divergence_threshold=0.02, transport_learning_rate=1e-4)
    if method == "local_ot_perturbed":
        return otf.local_ot(otf.local_windows(model.geometry, 3.0, 1.0), num_iterations=(1024, 64),
                            enkf_layer=True, inflation=local["inflation"],
                            batch_size=local["ot_batch_size"])
    return lorenz96_update(method, model)


def run(method, model, keys, observations, num_particles):
    """``method``: a name (``build``) or an update."""
    update = build(method, model) if isinstance(method, str) else method

    @jax.jit
    def filters(keys, observations):
        def one(key, y):
            result = otf.run_filter(key, model, update, y, num_particles, save_every=0)
            flags = diverged_flags(result.info)  # split_likelihood: any of its steps
            return result.mean, (jnp.zeros(y.shape[0], bool) if flags is None else flags)
        return jax.vmap(one)(keys, observations)

    compiled = filters.lower(keys, observations).compile()
    start = time.perf_counter()
    means, diverged = jax.block_until_ready(compiled(keys, observations))
    return np.asarray(means), np.asarray(diverged), time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--operator", choices=("linear", "square", "abs"), default="linear")
    parser.add_argument("--noise", type=float, default=1.0, help="observation noise std")
    parser.add_argument("--every", type=int, default=1, help="RK4 steps (0.05) between observations")
    parser.add_argument("--simulations", type=int, default=4)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--methods", default="letkf,letkf_step,layer,local_ot")
    parser.add_argument("--out", default="benchmarks/results/ot_lorenz96")
    parser.add_argument("--no-low-trend", action="store_true",
                        help="diagnostic: switch off the OT updates' lower bound on the innovation trend (a second "
                             "step of split_likelihood sees the observation against an analysed ensemble and "
                             "the tempered noise, an innovation below 1 by design)")
    args = parser.parse_args()
    if args.no_low_trend:
        from ot_filter.transport import divergence
        divergence.MIN_INNOVATION_TREND = -1e9
    os.makedirs(args.out, exist_ok=True)
    model = lorenz96(dim=40, observation_operator=args.operator, observation_noise_std=args.noise,
                     steps_per_observation=args.every)
    truth_key, filter_key = jax.random.split(cell_key(args.seed, 40, 0))  # the runner's truths
    states, observations = simulate_truths(truth_key, model, args.steps, args.simulations)
    keys = jax.random.split(filter_key, args.simulations)
    setting = dict(operator=args.operator, noise=args.noise, every=args.every, simulations=args.simulations,
                   steps=args.steps, particles=args.particles, seed=args.seed, local=LORENZ96_LOCAL,
                   **({"no_low_trend": True} if args.no_low_trend else {}))
    path = os.path.join(args.out, f"ot_lorenz96_{args.operator}.json")
    results = json.load(open(path)) if os.path.exists(path) else {}
    if results.get("setting") != json.loads(json.dumps(setting)):
        results = {"setting": setting, "rows": {}}
    late = slice(args.steps // 2, None)
    for method in args.methods.split(","):
        means, diverged, seconds = run(method, model, keys, observations, args.particles)
        rmse = np.asarray(jax.vmap(metrics.rmse)(means, states))[:, late].mean(axis=1)
        rmse = np.where(np.isfinite(rmse), rmse, np.inf)
        results["rows"][method] = dict(rmse=rmse.tolist(), mean=float(rmse.mean()),
                                       se=float(rmse.std(ddof=1) / np.sqrt(len(rmse))) if len(rmse) > 1 else 0.0,
                                       fallbacks=int(diverged.sum()), seconds=seconds)
        print(f"{method}: RMSE {rmse.mean():.4f} ({np.round(rmse, 4).tolist()}), "
              f"{int(diverged.sum())} fallbacks, {seconds:.1f} s", flush=True)
        write_text_atomic(path, json.dumps(results, indent=1))
    lines = [f"# Lorenz-96, {args.operator} observations (noise std {args.noise}, every {args.every} "
             f"RK4 steps), N = {args.particles}, {args.simulations} simulations of {args.steps} steps",
             "", "RMSE of the filter mean over the second half (mean ± standard error over the simulations).", "",
             *([results["note"], ""] if results.get("note") else []),
             "The paired column is the mean over the simulations of (method's RMSE - LETKF's RMSE) on the same "
             "truth, ± its standard error: the chaotic spread between truths cancels in it.", "",
             "| method | RMSE | / LETKF | - LETKF (paired) | fallbacks | seconds |", "|---|--:|--:|--:|--:|--:|"]
    reference = results["rows"].get("letkf")
    for method, row in results["rows"].items():
        ratio = f"{row['mean'] / reference['mean']:.2f}" if reference else "–"
        paired = "–"
        if reference and len(row["rmse"]) > 1:
            difference = np.asarray(row["rmse"]) - np.asarray(reference["rmse"])
            paired = f"{difference.mean():+.4f} ± {difference.std(ddof=1) / np.sqrt(len(difference)):.4f}"
        lines.append(f"| {method} | {row['mean']:.4f} ± {row['se']:.4f} | {ratio} | {paired} | {row['fallbacks']} | "
                     f"{row['seconds']:.0f} |")
    write_text_atomic(os.path.join(args.out, f"ot_lorenz96_{args.operator}.md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
