"""Amortised OT filtering: the forecast bank, offline training, the update, the choice among
candidate maps, saving and loading.

The tests on the map trained for the Kalman comparison (``trained``: 12,000 offline iterations,
about a minute) are ``long``; the bank, batch and context tests are quick."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.amortised import (
    MapScore,
    AmortisedMap,
    ForecastBank,
    MapMismatchError,
    bank_batch,
    forecast_bank,
    load_map,
    map_recipe,
    save_map,
    score_map,
    select_map,
    collect_forecasts,
    distil_map,
    split_bank,
    stack_banks,
    train_amortised,
    train_amortised_seeds,
    train_maps,
)
from ot_filter.progress import progress_listener
from ot_filter.transport.divergence import CHECK_ROWS
from ot_filter.transport.standardisation import Standardisation
from ot_filter.updates.ot import networks

# A stationary 1-D linear-Gaussian model: the Kalman filter is the exact reference.
A, Q, R = 0.9, 0.3, 0.5


def scalar_model():
    return otf.models.linear_gaussian([[A]], [[Q]], [[1.0]], [[R]], [0.0], [[1.0]])


@pytest.fixture(scope="module")
def trained():
    """A map trained offline on the scalar model (2 rounds: EnKF forecasts, then its own), without
    the context inputs (a stationary linear-Gaussian filter meets one prior shape; the context
    is then noise the map must learn to ignore, which takes longer: 0.10 instead of 0.05 for the
    error below after 12,000 iterations)."""
    reports = []
    with progress_listener(lambda done, total: reports.append((done, total))):
        trained_map, histories = train_amortised(
            jax.random.key(0), scalar_model(), model_name="scalar-lg", num_simulations=20, num_steps=30,
            num_particles=200, burn_in=5, rounds=2, num_iterations=12_000, chunks=3, width=32, batch_size=64,
            ensembles_per_batch=4, context=False,
        )
    return trained_map, histories, reports


@pytest.fixture(scope="module")
def contextual():
    """A briefly trained map with the context inputs (for saving, loading and reuse)."""
    trained_map, _ = train_amortised(
        jax.random.key(1), scalar_model(), model_name="scalar-lg", num_simulations=6, num_steps=10,
        num_particles=100, rounds=1, num_iterations=200, chunks=2, width=8, batch_size=32, ensembles_per_batch=4,
    )
    return trained_map


def test_forecast_bank_standardises_each_ensemble_and_holds_its_gain():
    model = scalar_model()
    analyses = jax.random.normal(jax.random.key(1), (3, 4, 100, 1)) * jnp.arange(1.0, 4.0)[:, None, None, None]
    bank = forecast_bank(jax.random.key(2), model, analyses)
    assert bank.particles.shape == (12, 100, 1) and bank.gain.shape == (12, 1, 1)
    standard = jax.vmap(lambda s, x: s.standardise_x(x))(bank.scaling, bank.particles)
    np.testing.assert_allclose(standard.mean(axis=1), 0.0, atol=1e-5)
    np.testing.assert_allclose(standard.std(axis=1), 1.0, rtol=1e-4)
    # Spread grows with the analyses' (propagated with A = 0.9 and noise Q).
    spread = np.asarray(bank.scaling.x_scale[:, 0]).reshape(3, 4).mean(axis=1)
    assert spread[0] < spread[1] < spread[2]
    assert np.all(np.isfinite(np.asarray(bank.gain))) and np.all(np.asarray(bank.gain) > 0)


def test_a_mini_batch_draws_pairs_and_copies_from_one_ensemble():
    # Ensemble e holds the values 100 e + [0, 1): any pair or copy from another ensemble shows.
    count, num = 6, 50
    particles = (100.0 * jnp.arange(count)[:, None, None]
                 + jax.random.uniform(jax.random.key(3), (count, num, 1)))
    scaling = Standardisation(jnp.zeros((count, 1)), jnp.ones((count, 1)), jnp.zeros((count, 1)), jnp.ones((count, 1)))
    bank = ForecastBank(particles, scaling, jnp.arange(count, dtype=jnp.float32)[:, None, None],
                        jnp.zeros((count, 5)))
    batch = bank_batch(jax.random.key(4), bank, lambda key, x: x, batch_size=24, ensembles_per_batch=3,
                       enkf_layer=True)
    x, xbar = np.asarray(batch.x[:, 0]).reshape(3, 8), np.asarray(batch.xbar[:, 0]).reshape(3, 8)
    ensemble = np.floor(x / 100)
    assert np.all(ensemble == ensemble[:, :1]) and np.all(np.floor(xbar / 100) == ensemble)
    # Each pair carries its own ensemble's gain; observations are simulated at the pair (here y = x).
    np.testing.assert_array_equal(np.asarray(batch.gain[:, 0, 0]).reshape(3, 8), ensemble)
    np.testing.assert_array_equal(batch.y, batch.x)
    # Not always the same ensemble: the 3 sub-batches of a few draws cover several ensembles.
    seen = {int(np.floor(bank_batch(jax.random.key(k), bank, lambda key, x: x, batch_size=24, ensembles_per_batch=3,
                                    enkf_layer=False).x[0, 0] / 100)) for k in range(10)}
    assert len(seen) >= 3


def test_split_bank_holds_out_the_last_ensembles():
    bank = ForecastBank(jnp.arange(10.0)[:, None, None] * jnp.ones((10, 4, 1)),
                        Standardisation(*(jnp.zeros((10, 1)),) * 4), jnp.zeros((10, 1, 1)), jnp.zeros((10, 5)))
    training, validation = split_bank(bank, 0.2)
    assert training.num_ensembles == 8 and validation.num_ensembles == 2
    np.testing.assert_array_equal(validation.particles[:, 0, 0], [8.0, 9.0])
    with pytest.raises(ValueError, match="validation_fraction"):
        split_bank(bank, 1.0)


@pytest.mark.long
def test_offline_training_reports_progress_and_a_finite_validation_curve(trained):
    trained_map, histories, reports = trained
    assert len(histories) == 2 and reports == [(1, 3), (2, 3), (3, 3)] * 2
    for history in histories:
        assert history.iterations.tolist() == [2000, 4000, 6000]
        assert np.all(np.isfinite(history.validation_loss)) and np.all(np.isfinite(history.training_loss))
    assert trained_map.info["rounds"] == 2 and trained_map.info["iterations"] == 12_000
    assert trained_map.config.state_dim == 1 and trained_map.config.observation_dim == 1


def _kalman_and_filters(update, num_particles=200, steps=40):
    model = scalar_model()
    _, observations = otf.simulate(jax.random.key(7), model, steps)
    exact = otf.kalman_filter(model, observations)
    result = otf.run_filter(jax.random.key(8), model, update, observations, num_particles)
    return exact, result


def _assert_matches_kalman(update):
    """The filter's mean within 3 Monte-Carlo errors of the Kalman filter's (N = 200, after 5
    steps), its variance within a third, no step fallen back; returns its result."""
    exact, result = _kalman_and_filters(update)
    monte_carlo = float(np.sqrt(np.mean(exact.cov[5:, 0, 0]) / 200))
    error = np.sqrt(np.mean((np.asarray(result.mean[5:, 0]) - np.asarray(exact.mean[5:, 0])) ** 2))
    assert error < 3 * monte_carlo, (error, monte_carlo)
    variance_ratio = np.mean(np.asarray(result.spread[5:]) ** 2) / np.mean(np.asarray(exact.cov[5:, 0, 0]))
    assert 0.75 < variance_ratio < 1.33, variance_ratio
    assert not np.any(np.asarray(result.info.diverged))
    return result


@pytest.mark.long
def test_the_amortised_filter_matches_the_kalman_filter_without_training_online(trained):
    # The posterior mean's Monte-Carlo error at N = 200 is sqrt(P_a / N) ~ 0.036 (P_a ~ 0.26);
    # the prior mean is off by K |y - x_f| ~ 0.5: a map that does not condition fails by far.
    trained_map, _, _ = trained
    result = _assert_matches_kalman(otf.amortised_ot(trained_map))
    assert np.all(np.isinf(np.asarray(result.info.loss))) or result.info.loss.shape[-1] == 0
    assert np.all(np.isfinite(np.asarray(result.info.final_loss)))


@pytest.mark.long
def test_without_training_the_loss_is_the_map_s_j_on_the_prior_s_first_pairs(trained):
    # The loss test of a map used as is reads J on the first CHECK_ROWS pairs of the prior with
    # their own simulated observations, the copies shifted by one row; the potential's spread
    # is f's over the same pairs. Computed here from those rows directly.
    trained_map, _, _ = trained
    model, update = scalar_model(), otf.amortised_ot(trained_map)
    particles = 0.5 + jax.random.normal(jax.random.key(3), (200, 1))
    state = update.init(jax.random.key(4), particles, model)
    _, after, info = update.apply(jax.random.key(5), state, particles, jnp.array([1.2]), model)
    scaling = after.standardisation
    xs = np.asarray(scaling.standardise_x(particles))[:CHECK_ROWS]
    ys = np.asarray(scaling.standardise_y(after.simulated_observations))[:CHECK_ROWS]
    copies = np.roll(np.arange(CHECK_ROWS), -1)
    _, structure = map_recipe(trained_map.config)
    potential_net, transport_net = networks(structure)
    params = trained_map.params
    f = lambda x, y: np.asarray(potential_net.apply(params.potential, jnp.asarray(x), jnp.asarray(y)))  # noqa: E731
    moved = np.asarray(transport_net.apply(params.transport, jnp.asarray(xs[copies]), jnp.asarray(ys)))
    joint = f(xs, ys)
    expected = joint.mean() + np.mean(0.5 * np.sum((moved - xs[copies]) ** 2, axis=1) - f(moved, ys))
    np.testing.assert_allclose(float(info.final_loss), expected, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(float(info.potential_spread), joint.std(), rtol=1e-4)


@pytest.mark.long
def test_an_unconditioned_map_fails_the_same_check(trained):
    # The control of the test above: the untrained anchor (a random map) with no online training.
    trained_map, _, _ = trained
    untrained = trained_map._replace(params=jax.tree.map(jnp.zeros_like, trained_map.params))
    exact, result = _kalman_and_filters(otf.amortised_ot(untrained))
    monte_carlo = float(np.sqrt(np.mean(exact.cov[5:, 0, 0]) / 200))
    error = np.sqrt(np.mean((np.asarray(result.mean[5:, 0]) - np.asarray(exact.mean[5:, 0])) ** 2))
    assert error > 3 * monte_carlo


def test_a_map_used_as_is_that_does_not_condition_falls_back_to_the_enkf(trained):
    # The zero map is the identity: it keeps the prior. On a prior of std 10 with R = 0.5 the
    # EnKF keeps std 0.7, so the transported spread is 14 times the EnKF's: the step falls back
    # (to the dense perturbed-EnKF reference). On a prior of std 1 it is 1.7 times: the map is used.
    from conftest import perturbed_enkf_reference

    trained_map, _, _ = trained
    identity = otf.amortised_ot(trained_map._replace(params=jax.tree.map(jnp.zeros_like, trained_map.params)))
    model, y = scalar_model(), jnp.array([3.0])
    for scale, falls_back in ((10.0, True), (1.0, False)):
        particles = scale * jax.random.normal(jax.random.key(5), (400, 1))
        state = identity.init(jax.random.key(6), particles, model)
        posterior, after, info = identity.apply(jax.random.key(7), state, particles, y, model)
        assert bool(info.diverged) == falls_back and float(info.predictive_z) < 10.0
        if falls_back:
            expected = perturbed_enkf_reference(particles, after.simulated_observations, y, after.standardisation,
                                                model=model)
            np.testing.assert_allclose(posterior, expected, rtol=1e-5, atol=1e-5)
        else:
            np.testing.assert_allclose(posterior, particles, rtol=1e-5, atol=1e-5)


def _errors_truth_by_truth(key, truth_model, model, trained_map, num_simulations, num_steps, num_particles, skip):
    """``score_map``'s per-truth errors, unjitted: each truth of ``truth_model`` filtered with
    ``model`` and the map's (a), the squared error of the mean after ``skip`` steps."""
    truth_key, filter_key = jax.random.split(key)
    errors = []
    for truth, filter_ in zip(jax.random.split(truth_key, num_simulations), jax.random.split(filter_key, num_simulations)):
        states, observations = otf.simulate(truth, truth_model, num_steps)
        result = otf.run_filter(filter_, model, otf.amortised_ot(trained_map), observations, num_particles)
        errors.append(np.mean((np.asarray(result.mean[skip:]) - np.asarray(states[skip:])) ** 2))
    return errors


@pytest.mark.long
def test_the_selection_keeps_the_map_whose_filter_tracks_simulated_truths(trained):
    # Both candidates filter the same 8 simulated truths (one compiled, vmapped program per map);
    # the score is recomputed here truth by truth, unjitted: the MSE of the filter's mean to the
    # truth after the first 5 steps.
    trained_map, _, _ = trained
    untrained = trained_map._replace(params=jax.tree.map(jnp.zeros_like, trained_map.params))
    model, key = scalar_model(), jax.random.key(21)
    chosen, scores = select_map(key, model, {"untrained": untrained, "trained": trained_map}, num_simulations=8,
                                num_steps=30, num_particles=200, skip_steps=5)
    assert chosen == "trained" and set(scores) == {"untrained", "trained"}
    errors = _errors_truth_by_truth(key, model, model, trained_map, 8, 30, 200, 5)
    np.testing.assert_allclose(scores["trained"].per_simulation, errors, rtol=1e-4)
    np.testing.assert_allclose(scores["trained"].mse, np.mean(errors), rtol=1e-4)
    assert scores["trained"].stderr == pytest.approx(np.std(errors, ddof=1) / np.sqrt(8), rel=1e-3)
    # Paired over the same truths, the unconditioned map is behind by more than 3 standard errors.
    assert np.all(np.isfinite(scores["untrained"].per_simulation))
    difference = scores["untrained"].per_simulation - scores["trained"].per_simulation
    assert difference.mean() > 3 * difference.std(ddof=1) / np.sqrt(8), difference


def test_the_selection_checks_its_candidates(contextual):
    model = scalar_model()
    options = dict(num_simulations=2, num_steps=4, num_particles=20)
    with pytest.raises(ValueError, match="at least one map"):
        select_map(jax.random.key(0), model, {}, **options)
    other = contextual._replace(config=contextual.config._replace(model="another"))
    with pytest.raises(ValueError, match="maps of one model"):
        select_map(jax.random.key(0), model, {"a": contextual, "b": other}, **options)
    with pytest.raises(ValueError, match="skip_steps must be in"):
        select_map(jax.random.key(0), model, {"a": contextual}, skip_steps=4, **options)
    with pytest.raises(ValueError, match="skip_steps must be an int"):
        select_map(jax.random.key(0), model, {"a": contextual}, skip_steps=1.5, **options)
    planar = otf.models.linear_gaussian(np.eye(2), np.eye(2), np.eye(2), np.eye(2), np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match=r"model has \(state, observation\) dimensions \(2, 2\), the map 'scalar-lg'"):
        select_map(jax.random.key(0), planar, {"a": contextual}, **options)
    # Stored scores are strict JSON: a truth whose filter was not finite is null, not Infinity.
    record = MapScore(float("inf"), float("inf"), np.array([0.5, np.inf]), 3, 1.0).record()
    assert record["mse"] is None and record["stderr"] is None and record["per_simulation"] == [0.5, None]
    json.dumps(record, allow_nan=False)


def test_the_selection_scores_on_truths_of_the_truth_model(contextual):
    # Truths from a model whose initial law is far from the filter's (like Lorenz-63's, which
    # start at 25 against the filter's prior at 0); the filter keeps its own model. Recomputed
    # truth by truth, unjitted.
    model, key = scalar_model(), jax.random.key(8)
    far = otf.models.linear_gaussian([[A]], [[Q]], [[1.0]], [[R]], [30.0], [[1.0]])
    options = dict(num_simulations=3, num_steps=6, num_particles=50, skip_steps=1)
    score = score_map(key, model, contextual, truth_model=far, **options)
    errors = _errors_truth_by_truth(key, far, model, contextual, 3, 6, 50, 1)
    np.testing.assert_allclose(score.per_simulation, errors, rtol=1e-4)
    # The default is the filter's own model (other truths, other errors).
    own = score_map(key, model, contextual, **options).per_simulation
    np.testing.assert_array_equal(own, score_map(key, model, contextual, truth_model=model, **options).per_simulation)
    assert not np.allclose(own, errors, rtol=0.1)
    chosen, scores = select_map(key, model, {"a": contextual}, truth_model=far, **options)
    np.testing.assert_allclose(scores["a"].per_simulation, errors, rtol=1e-4)
    planar = otf.models.linear_gaussian(np.eye(2), np.eye(2), np.eye(2), np.eye(2), np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match=r"truth_model has \(state, observation\) dimensions \(2, 2\)"):
        score_map(key, model, contextual, truth_model=planar, **options)


def test_a_selection_where_no_filter_stays_finite_is_refused(contextual):
    # Truths that overflow (x_t = 1e30 x_{t-1}): every candidate's error is +inf, none is kept.
    exploding = otf.models.linear_gaussian([[1e30]], [[Q]], [[1.0]], [[R]], [0.0], [[1.0]])
    with pytest.raises(ValueError, match="no candidate's filter stayed finite"):
        select_map(jax.random.key(0), exploding, {"a": contextual, "b": contextual}, num_simulations=2, num_steps=4,
                   num_particles=20)


def test_overrides_may_not_set_what_the_candidates_differ_by(tmp_path):
    from ot_filter.experiments.amortised import map_for

    with pytest.raises(ValueError, match=r"overrides \['enkf_layer'\] are what the candidates"):
        map_for(str(tmp_path / "map"), jax.random.key(0), "lorenz63", enkf_layer=True)
    with pytest.raises(ValueError, match=r"overrides \['training_fold'\] are what the candidates"):
        map_for(str(tmp_path / "map"), jax.random.key(0), "dynamic", training_fold=2)
    # A training fold is an int >= 0, and not the one that draws the held-out truths.
    for fold, message in ((0.5, "must be an int >= 0"), (-1, "must be an int >= 0"), (1000, "may not be 1000")):
        with pytest.raises(ValueError, match=message):
            map_for(str(tmp_path / "map"), jax.random.key(0), "dynamic",
                    candidates={"plain": {}, "other": {"training_fold": fold}})
    assert not (tmp_path / "map").exists()  # refused before anything was trained
    # A network option (also one of MAP_OPTIONS) may be overridden: a candidate stored with the
    # defaults is then stale, and refused before anything is trained.
    stored = tmp_path / "widened" / "candidates" / "plain"
    stored.mkdir(parents=True)
    (stored / "map.json").write_text("{}")
    (stored / "options.json").write_text(json.dumps({"width": 64}))
    with pytest.raises(ValueError, match="trained with other options"):
        map_for(str(tmp_path / "widened"), jax.random.key(0), "dynamic", candidates={"plain": {}}, width=16)


def test_a_gate_s_further_trainings_are_each_setting_from_its_next_unused_fold(tmp_path):
    from ot_filter.experiments.amortised import CANDIDATES, SELECTION_FOLD, further_trainings, map_for

    first = further_trainings(CANDIDATES)
    assert first == {"plain_training_2": {"training_fold": 2},
                     "enkf_layer_training_2": {"enkf_layer": True, "training_fold": 2}}
    assert further_trainings({**CANDIDATES, **first}) == {
        "plain_training_3": {"training_fold": 3}, "enkf_layer_training_3": {"enkf_layer": True, "training_fold": 3}}
    # a setting's folds need not be consecutive; the held-out truths' fold is skipped
    assert further_trainings({"wide": {"width": 8, "training_fold": SELECTION_FOLD - 1}, "narrow": {"width": 4}}) == {
        "wide_training_1001": {"width": 8, "training_fold": SELECTION_FOLD + 1},
        "narrow_training_1": {"width": 4, "training_fold": 1}}
    with pytest.raises(ValueError, match="already has a 'plain_training_1' of other settings"):
        further_trainings({"plain": {}, "plain_training_1": {"width": 8}})
    for gate in (0, True, "1.25", float("inf"), float("nan")):
        message = "gate must be a finite ratio > 0"
        with pytest.raises(ValueError, match=message):
            map_for(str(tmp_path / "map"), jax.random.key(0), "lorenz63", gate=gate)
    with pytest.raises(ValueError, match="extra_waves must be an int >= 0"):
        map_for(str(tmp_path / "map"), jax.random.key(0), "lorenz63", extra_waves=-1)
    assert not (tmp_path / "map").exists()  # refused before anything was trained


def test_the_map_s_batch_is_half_the_online_update_s_and_at_least_256_and_averaged_above_n_4():
    from ot_filter.experiments.amortised import MAP_OPTIONS, map_options
    from ot_filter.updates.ot import default_sizes

    # ot()'s batch: 128 (n <= 2), 256 (n = 3), 512 (n = 4), 1024 (n >= 5).
    assert [default_sizes(n)[1] for n in (2, 3, 4, 5, 10, 50)] == [128, 256, 512, 1024, 1024, 1024]
    assert [map_options(n)["batch_size"] for n in (1, 2, 3, 4, 5, 10, 50)] == [256] * 4 + [512] * 3
    assert {k: v for k, v in map_options(10).items() if k != "batch_size"} == {
        **{k: v for k, v in MAP_OPTIONS.items() if k != "batch_size"}, "average_chunks": 20}
    # the iterates' average where it was measured (above n = 4), the last iterate below
    assert [map_options(n).get("average_chunks", 0) for n in (2, 4, 5, 10)] == [0, 0, 20, 20]
    # Lorenz-63: the last round averaged, its last iterate (b)'s start as without averaging
    assert map_options(3, "lorenz63") == dict(MAP_OPTIONS, average_chunks=20, average_rounds="last")
    assert "average_rounds" not in map_options(10)


def test_the_offline_stage_selects_on_truths_like_the_experiment_s():
    from ot_filter.experiments.amortised import experiment_model, selection_truths
    from ot_filter.experiments.lorenz63 import lorenz63_models

    # Lorenz-63: the experiment's truth model (no process noise, started at 25, not the filter's
    # prior at 0), the settling time t <= 1.5 (150 steps of 0.01) left out of the score.
    truth_model, skip = selection_truths("lorenz63", observed=(0,), num_steps=500)
    assert skip == 150
    assert jax.tree.structure(truth_model) == jax.tree.structure(lorenz63_models((0,))[0])
    starts = jax.vmap(truth_model.sample_initial)(jax.random.split(jax.random.key(0), 400))
    np.testing.assert_allclose(starts.mean(axis=0), 25.0, atol=4 * 10.0 / np.sqrt(400))
    state = jnp.array([1.0, 2.0, 3.0])
    truth_step = truth_model.sample_transition(jax.random.key(1), state)
    np.testing.assert_array_equal(truth_step, truth_model.sample_transition(jax.random.key(2), state))
    assert truth_model.observation_function(state).shape == (1,)
    # runs too short to settle: the first tenth, as on the dynamic example
    assert selection_truths("lorenz63", num_steps=100)[1] == 10
    model, skip = selection_truths("dynamic", dim=3, num_steps=20)
    assert skip == 2
    assert jax.tree.structure(model) == jax.tree.structure(experiment_model("dynamic", 3))
    np.testing.assert_array_equal(model.sample_initial(jax.random.key(3)),
                                  experiment_model("dynamic", 3).sample_initial(jax.random.key(3)))


def test_the_dynamic_example_s_bank_grows_with_the_dimension():
    from ot_filter.experiments.amortised import OFFLINE, offline_options

    # 15 n simulations of 20 steps (300 ensembles per coordinate), at least 50; above n = 4 a
    # fourth round of 7,000 iterations; Lorenz-63 as OFFLINE.
    assert [offline_options("dynamic", n)["num_simulations"] for n in (1, 2, 3, 4, 5, 10)] == [50, 50, 50, 60, 75, 150]
    assert [offline_options("dynamic", n)["rounds"] for n in (1, 2, 4, 5, 10)] == [3, 3, 3, 4, 4]
    assert [offline_options("dynamic", n)["num_iterations"] for n in (2, 4, 5, 10)] == [21_000, 21_000, 28_000, 28_000]
    assert offline_options("dynamic", 2) == OFFLINE["dynamic"]
    assert offline_options("dynamic", 10)["num_steps"] == OFFLINE["dynamic"]["num_steps"]
    assert offline_options("lorenz63", 3) == OFFLINE["lorenz63"]


def test_warm_started_budget_covers_half_the_online_filter_s_pairs_at_its_floor():
    from ot_filter.amortised import AmortisedMap, MapConfig
    from ot_filter.experiments.amortised import WARM_OPTIONS, warm_options

    def sized(state_dim, batch_size):  # warm_options reads the map's sizes only
        config = MapConfig("dynamic", state_dim, state_dim, 64, 1, "relu", False, 10, batch_size, 1e-4, 1.0, 1e-3,
                           1.0, True)
        return AmortisedMap(None, None, config, {})

    # The online filter's floor: 64 iterations of ot()'s batch (128 at n = 2, 1024 at n = 10).
    # n = 2: half of 64 x 128 pairs is 16 iterations of 256, below the measured (128, 32): kept.
    assert (warm_options(sized(2, 256), "dynamic") == WARM_OPTIONS["dynamic"]
            == {"num_iterations": (128, 32), "warm_from": "average"})
    # n = 10: 32,768 pairs, 64 iterations of the map's 512 (128 of 256); first stays 4 x floor.
    assert warm_options(sized(10, 512), "dynamic") == {"num_iterations": (256, 64), "warm_from": "average"}
    assert warm_options(sized(10, 256), "dynamic") == {"num_iterations": (512, 128), "warm_from": "average"}
    assert warm_options(sized(3, 256), "lorenz63") == WARM_OPTIONS["lorenz63"]


@pytest.mark.long
def test_restarted_steps_start_from_the_offline_map_every_time(trained):
    trained_map, _, _ = trained
    model = scalar_model()
    update = otf.amortised_ot(trained_map, num_iterations=20, restart=True)
    particles = jax.random.normal(jax.random.key(9), (200, 1))
    state = update.init(jax.random.key(10), particles, model)
    first, after, info = update.apply(jax.random.key(11), state, particles, jnp.array([0.7]), model)
    assert info.loss.shape == (20,) and np.all(np.isfinite(np.asarray(info.loss)))
    moved = jax.tree.map(lambda a, b: bool(jnp.any(a != b)), after.training.params, trained_map.params)
    assert any(jax.tree.leaves(moved))  # the step fine-tuned the map ...
    again, _, _ = update.apply(jax.random.key(11), after, particles, jnp.array([0.7]), model)
    np.testing.assert_array_equal(again, first)  # ... but the next step starts from the offline one


@pytest.mark.long
def test_warm_started_steps_continue_from_the_step_before_with_a_halving_budget(trained):
    trained_map, _, _ = trained
    model = scalar_model()
    update = otf.amortised_ot(trained_map, num_iterations=(16, 4))
    particles = jax.random.normal(jax.random.key(9), (200, 1))
    state = update.init(jax.random.key(10), particles, model)
    for got, want in zip(jax.tree.leaves(state.training.params), jax.tree.leaves(trained_map.params)):
        np.testing.assert_array_equal(got, want)  # the first step starts from the offline map
    first, after, info = update.apply(jax.random.key(11), state, particles, jnp.array([0.7]), model)
    assert np.all(np.isfinite(np.asarray(info.loss)))  # 16 iterations, all recorded
    again, later, info = update.apply(jax.random.key(11), after, particles, jnp.array([0.7]), model)
    assert int(np.sum(np.isfinite(np.asarray(info.loss)))) == 8  # halved
    assert not np.array_equal(np.asarray(again), np.asarray(first))  # from the fine-tuned map
    with pytest.raises(ValueError, match="floor <= first"):
        otf.amortised_ot(trained_map, num_iterations=(4, 16))


@pytest.mark.long
def test_no_online_training_leaves_the_map_as_it_is_and_jit_agrees(trained):
    trained_map, _, _ = trained
    model = scalar_model()
    update = otf.amortised_ot(trained_map)
    particles = jax.random.normal(jax.random.key(12), (100, 1))
    state = update.init(jax.random.key(13), particles, model)
    posterior, after, _ = update.apply(jax.random.key(14), state, particles, jnp.array([1.0]), model)
    for got, want in zip(jax.tree.leaves(after.training.params), jax.tree.leaves(trained_map.params)):
        np.testing.assert_array_equal(got, want)
    jitted = jax.jit(update.apply, static_argnums=())(jax.random.key(14), state, particles, jnp.array([1.0]), model)
    np.testing.assert_allclose(jitted[0], posterior, rtol=1e-6, atol=1e-6)
    # The map is the one transport applies.
    np.testing.assert_allclose(update.transport(after, particles, jnp.array([1.0])), posterior, rtol=1e-6, atol=1e-6)


def test_another_map_of_the_same_networks_reuses_the_compiled_filter(contextual):
    from ot_filter.filtering import _run_filter

    trained_map = contextual
    model = scalar_model()
    _, observations = otf.simulate(jax.random.key(15), model, 10)
    otf.run_filter(jax.random.key(16), model, otf.amortised_ot(trained_map), observations, 50)
    size = _run_filter._cache_size()
    other = trained_map._replace(params=jax.tree.map(lambda a: a * 0.5, trained_map.params),
                                 context_scaling=jax.tree.map(lambda a: a + 1.0, trained_map.context_scaling))
    otf.run_filter(jax.random.key(16), model, otf.amortised_ot(other), observations, 50)
    assert _run_filter._cache_size() == size


@pytest.mark.long
@pytest.mark.parametrize("which", ["plain", "contextual"])
def test_a_saved_map_reloads_bit_identically_and_filters_identically(which, trained, contextual, tmp_path):
    trained_map = trained[0] if which == "plain" else contextual
    assert (trained_map.context_scaling is None) == (which == "plain")
    save_map(tmp_path / "map", trained_map)
    loaded = load_map(tmp_path / "map", model="scalar-lg", state_dim=1, observation_dim=1)
    assert isinstance(loaded, AmortisedMap) and loaded.config == trained_map.config
    for got, want in zip(jax.tree.leaves((loaded.params, loaded.context_scaling)),
                         jax.tree.leaves((trained_map.params, trained_map.context_scaling))):
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
    record = json.loads((tmp_path / "map" / "map.json").read_text())
    assert set(record["versions"]) == {"ot_filter", "jax", "flax"} and record["config"]["model"] == "scalar-lg"
    assert record["versions"]["ot_filter"] == otf.__version__ and record["versions"]["jax"] == jax.__version__
    model = scalar_model()
    _, observations = otf.simulate(jax.random.key(17), model, 15)
    first = otf.run_filter(jax.random.key(18), model, otf.amortised_ot(trained_map, 3), observations, 100)
    second = otf.run_filter(jax.random.key(18), model, otf.amortised_ot(loaded, 3), observations, 100)
    np.testing.assert_array_equal(first.mean, second.mean)
    np.testing.assert_array_equal(first.final_particles, second.final_particles)


@pytest.mark.long
def test_a_map_for_another_model_is_refused(trained, tmp_path):
    trained_map, _, _ = trained
    save_map(tmp_path / "map", trained_map)
    with pytest.raises(MapMismatchError, match="trained for model 'scalar-lg'.*asked for model 'lorenz63'"):
        load_map(tmp_path / "map", model="lorenz63")
    with pytest.raises(MapMismatchError, match="state dimension 1.*state_dim 3"):
        load_map(tmp_path / "map", state_dim=3)
    # A model of other dimensions, given the map directly, is refused at init.
    lorenz = otf.models.lorenz63()
    with pytest.raises(ValueError, match="trained for 'scalar-lg' with state dimension 1"):
        otf.run_filter(jax.random.key(0), lorenz, otf.amortised_ot(trained_map),
                       jnp.zeros((3, 3)), 10)
    # A parameter file that does not match its record.
    (tmp_path / "map" / "params.msgpack").write_bytes(b"\x80")
    with pytest.raises(MapMismatchError, match="SHA-256"):
        load_map(tmp_path / "map")
    with pytest.raises(FileNotFoundError, match="no amortised map"):
        load_map(tmp_path / "nothing")
    with pytest.raises(TypeError, match="AmortisedMap"):
        otf.amortised_ot(trained_map.params)


@pytest.mark.long  # two compilations of the training programs (2 seeds and 1), about a minute
def test_seeds_trained_together_are_the_maps_each_seed_trains_alone(x64):
    # One vmapped program for both seeds; seed 1's map, curves and context scaling must be the
    # ones train_amortised gives for its key alone (float64: the vmapped and the single
    # program differ only in rounding), and the two seeds must differ (their own data and init).
    options = dict(model_name="scalar-lg", num_simulations=6, num_steps=10, num_particles=100, rounds=1,
                   num_iterations=200, chunks=2, width=8, batch_size=32, ensembles_per_batch=4)
    keys = jax.random.split(jax.random.key(3), 2)
    maps, histories = train_amortised_seeds(keys, scalar_model(), **options)
    alone, alone_histories = train_amortised(keys[1], scalar_model(), **options)
    assert len(maps) == 2 and len(histories) == 2 and len(histories[1]) == 1
    assert maps[1].params.transport is not None and maps[0].info["seeds_trained_together"] == 2
    leaves = lambda tree: jax.tree.leaves(tree)  # noqa: E731
    for together, single in zip(leaves((maps[1].params, maps[1].context_scaling)),
                                leaves((alone.params, alone.context_scaling))):
        assert together.dtype == jnp.float64
        np.testing.assert_allclose(together, single, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(histories[1][0].validation_loss, alone_histories[0].validation_loss, rtol=1e-10)
    gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(leaves(maps[0].params), leaves(maps[1].params)))
    assert gap > 1e-2
    assert histories[0][0].validation_loss[-1] != histories[1][0].validation_loss[-1]


def test_an_averaged_map_is_the_mean_of_its_last_iterates():
    # Chunks are deterministic and keyed by their index, so 3 chunks of a 4-chunk training are
    # the 3-chunk training: averaging the last 2 of 4 is the mean of the two trainings' maps.
    # One chunk averaged is the last iterate, and the recorded J is the returned map's.
    options = dict(model_name="scalar-lg", num_simulations=6, num_steps=10, num_particles=100, rounds=1,
                   width=8, batch_size=32, ensembles_per_batch=4)
    key = jax.random.key(5)
    three, _ = train_amortised(key, scalar_model(), num_iterations=150, chunks=3, **options)
    four, four_histories = train_amortised(key, scalar_model(), num_iterations=200, chunks=4, **options)
    averaged, averaged_histories = train_amortised(key, scalar_model(), num_iterations=200, chunks=4,
                                                   average_chunks=2, **options)
    last, _ = train_amortised(key, scalar_model(), num_iterations=200, chunks=4, average_chunks=1, **options)
    leaves = jax.tree.leaves
    for mean, a, b, one, plain in zip(leaves(averaged.params), leaves(three.params), leaves(four.params),
                                      leaves(last.params), leaves(four.params)):
        np.testing.assert_allclose(mean, (a + b) / 2, rtol=1e-6, atol=1e-7)
        np.testing.assert_array_equal(one, plain)
    assert max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(leaves(three.params), leaves(four.params))) > 1e-3
    assert averaged.info["averaged_chunks"] == 2 and four.info["averaged_chunks"] == 0
    # the curves are the iterates' either way; the final J is the returned map's
    np.testing.assert_array_equal(averaged_histories[0].validation_loss, four_histories[0].validation_loss)
    assert last.info["final_validation_loss"] == pytest.approx(float(four_histories[0].validation_loss[-1]), rel=1e-6)
    assert averaged.info["final_validation_loss"] != pytest.approx(four.info["final_validation_loss"], rel=1e-6)
    for bad, match in [(5, "average_chunks must be at most chunks = 4"), (-1, "average_chunks")]:
        with pytest.raises(ValueError, match=match):
            train_amortised(key, scalar_model(), num_iterations=200, chunks=4, average_chunks=bad, **options)
    # the last iterate is kept beside the average (and only there)
    assert four.last_iterate is None
    for kept, want in zip(leaves(averaged.last_iterate), leaves(four.params)):
        np.testing.assert_array_equal(kept, want)


def test_averaging_the_last_round_only_leaves_the_rounds_and_the_last_iterate_unchanged():
    # With average_rounds="last" the rounds before the last train (and simulate their forecasts)
    # as without averaging, so the last iterate, where (b) starts, is the unaveraged training's
    # map bit for bit; averaging every round feeds the average into the next round's forecasts.
    options = dict(model_name="scalar-lg", num_simulations=6, num_steps=10, num_particles=100, rounds=2,
                   width=8, batch_size=32, ensembles_per_batch=4, num_iterations=200, chunks=2)
    key = jax.random.key(5)
    plain, plain_histories = train_amortised(key, scalar_model(), **options)
    last, last_histories = train_amortised(key, scalar_model(), average_chunks=2, average_rounds="last", **options)
    every, every_histories = train_amortised(key, scalar_model(), average_chunks=2, **options)
    leaves = jax.tree.leaves
    for kept, want in zip(leaves(last.last_iterate), leaves(plain.params)):
        np.testing.assert_array_equal(kept, want)
    np.testing.assert_array_equal(last_histories[0].validation_loss, plain_histories[0].validation_loss)
    np.testing.assert_array_equal(last_histories[1].validation_loss, plain_histories[1].validation_loss)
    assert max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(leaves(last.params), leaves(plain.params))) > 1e-4
    # every round averaged: the second round starts elsewhere
    assert not np.array_equal(every_histories[1].validation_loss, plain_histories[1].validation_loss)
    with pytest.raises(ValueError, match="average_rounds must be 'every' or 'last'"):
        train_amortised(key, scalar_model(), average_chunks=2, average_rounds="first", **options)


def test_warm_started_iterations_start_from_the_last_iterate_of_an_averaged_map(tmp_path):
    # (a) uses the average; (b) continues from the last iterate unless warm_from="average";
    # both survive saving and loading bit for bit.
    options = dict(model_name="scalar-lg", num_simulations=6, num_steps=10, num_particles=100, rounds=1,
                   width=8, batch_size=32, ensembles_per_batch=4)
    averaged, _ = train_amortised(jax.random.key(5), scalar_model(), num_iterations=200, chunks=4,
                                  average_chunks=2, **options)
    save_map(tmp_path / "map", averaged)
    loaded = load_map(tmp_path / "map", model="scalar-lg")
    for got, want in zip(jax.tree.leaves((loaded.params, loaded.last_iterate)),
                         jax.tree.leaves((averaged.params, averaged.last_iterate))):
        np.testing.assert_array_equal(got, want)
    model = scalar_model()
    _, observations = otf.simulate(jax.random.key(17), model, 8)

    def means(trained_map, *args, **kwargs):
        return otf.run_filter(jax.random.key(18), model, otf.amortised_ot(trained_map, *args, **kwargs),
                              observations, 50).mean

    only_average = loaded._replace(last_iterate=None)
    only_last = loaded._replace(params=loaded.last_iterate, last_iterate=None)
    np.testing.assert_array_equal(means(loaded), means(only_average))
    np.testing.assert_array_equal(means(loaded, 3), means(only_last, 3))
    np.testing.assert_array_equal(means(loaded, 3, warm_from="average"), means(only_average, 3))
    assert not np.array_equal(means(loaded, 3), means(only_average, 3))
    with pytest.raises(ValueError, match="warm_from must be"):
        otf.amortised_ot(loaded, 3, warm_from="first")


def test_seed_batches_are_checked():
    model = scalar_model()
    analyses = jax.random.normal(jax.random.key(0), (2, 3, 20, 1))
    bank = forecast_bank(jax.random.key(1), model, analyses)
    with pytest.raises(ValueError, match="as many ensembles"):
        stack_banks([bank, split_bank(bank, 0.5)[0]])
    stacked = stack_banks([bank, bank])
    assert stacked.particles.shape == (2, 6, 20, 1)
    with pytest.raises(ValueError, match="keys must be a 1-D array"):
        train_maps(jax.random.key(0), model, stacked, stacked, model_name="scalar-lg")
    with pytest.raises(ValueError, match=r"banks must be stacked per seed \(\[3, E, N, n\]"):
        train_maps(jax.random.split(jax.random.key(0), 3), model, stacked, stacked, model_name="scalar-lg")
    with pytest.raises(ValueError, match="starts must hold one map per seed"):
        train_maps(jax.random.split(jax.random.key(0), 2), model, stacked, stacked, model_name="scalar-lg",
                   starts=[])


def test_context_features_tell_a_two_mode_prior_from_a_gaussian_and_carry_the_scale():
    from ot_filter.transport.context import conditioning, context_features, fit_context_scaling

    gaussian = jax.random.normal(jax.random.key(20), (20_000, 1))
    two_modes = jnp.where(jax.random.bernoulli(jax.random.key(21), 0.5, (20_000, 1)), 1.0, -1.0)
    scaling = Standardisation(jnp.array([5.0]), jnp.array([2.0]), jnp.array([-1.0]), jnp.array([0.5]))
    features = context_features(scaling, gaussian)
    np.testing.assert_allclose(features[:4], [5.0, np.log(2.0), -1.0, np.log(0.5)], rtol=1e-6)
    # Skewness 0 (Monte-Carlo std sqrt(6 / 20000) = 0.017); excess kurtosis 0 for a Gaussian
    # (std sqrt(24 / 20000) = 0.035), -2 for +-1 (exactly, whatever the mode masses' draw).
    assert abs(float(features[4])) < 0.09 and abs(float(features[5])) < 0.18
    two_mode_features = context_features(scaling, two_modes)
    np.testing.assert_allclose(two_mode_features[5], -2.0 + 0.0 * two_mode_features[4], atol=0.02)
    # Unequal modes: +-1 with mass 0.8 / 0.2 (standardised) has skewness (0.2 - 0.8) / 0.4 = -1.5.
    skewed = jnp.where(jnp.arange(10_000) < 8_000, 1.0, -1.0)[:, None]
    skewed = (skewed - skewed.mean()) / skewed.std()
    np.testing.assert_allclose(context_features(scaling, skewed)[4], -1.5, rtol=1e-4)
    # Padding rows do not count.
    active = jnp.arange(20_000) < 10_000
    padded = jnp.where(active[:, None], two_modes, 100.0)
    assert float(context_features(scaling, padded, active)[5]) < -1.9
    normaliser = fit_context_scaling(jnp.stack([features, 2 * features]))
    assert np.all(np.asarray(normaliser.scale) > 0)
    assert conditioning(jnp.zeros((7, 2)), jnp.ones(5)).shape == (7, 7)
    assert conditioning(jnp.zeros((7, 2)), None).shape == (7, 2)


@pytest.mark.long  # worker processes (each imports JAX and compiles) and the same trainings in turn
def test_candidates_trained_in_worker_processes_are_the_candidates_trained_in_turn(tmp_path, monkeypatch):
    # map_for trains the offline candidates in worker processes, one a core (two threads of one
    # process hung in XLA's CPU runtime), in waves where there are more candidates than cores
    # (here 3 on 2: a wave of two, then one); the maps and the choice are those of training them
    # in turn.
    from ot_filter.amortised import load_map
    from ot_filter.experiments import processes
    from ot_filter.experiments.amortised import DYNAMIC_CANDIDATES, map_for

    monkeypatch.setattr(processes, "available_cores", lambda: 2)
    small = dict(num_particles=40, num_iterations=60, num_simulations=4)
    candidates = dict(DYNAMIC_CANDIDATES, plain_third_training={"training_fold": 2})
    maps = {}
    for workers in (True, False):
        directory = tmp_path / f"workers-{workers}"
        kept, histories = map_for(str(directory), jax.random.key(5), "dynamic", 2, workers=workers,
                                  candidates=candidates, **small)
        assert (histories is None) == workers  # a worker's curves are in its history.npz
        selection = kept.info["selection"]
        assert 0 < selection["offline_wall_seconds"] < 3600
        maps[workers] = (selection, {label: load_map(directory / "candidates" / label) for label in candidates})
        assert (directory / "candidates" / "plain" / "history.npz").exists()
    # The same scores up to rounding, so the same choice unless the two trainings tie.
    scores = {workers: {label: score["mse"] for label, score in maps[workers][0]["scores"].items()} for workers in maps}
    for label in scores[True]:
        assert scores[True][label] == pytest.approx(scores[False][label], rel=1e-3)
    ranked = sorted(scores[False].values())
    if ranked[1] - ranked[0] > 0.01 * ranked[0]:
        assert maps[True][0]["chosen"] == maps[False][0]["chosen"]
    for label in candidates:
        for got, want in zip(jax.tree.leaves(maps[True][1][label].params), jax.tree.leaves(maps[False][1][label].params)):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    # The dynamic example's second candidate is the plain map trained from fold_in(key, 1).
    folded, _ = map_for(str(tmp_path / "folded"), jax.random.fold_in(jax.random.key(5), 1), "dynamic", 2,
                        candidates={"plain": {}}, **small)
    for got, want in zip(jax.tree.leaves(folded.params), jax.tree.leaves(maps[False][1]["plain_second_training"].params)):
        np.testing.assert_array_equal(got, want)


@pytest.mark.long  # three small Lorenz-63 trainings, scored as (a), two of them as (b)
def test_lorenz63_s_stage_selects_b_s_start_by_b_s_score(tmp_path):
    # Lorenz-63 (WARM_SELECTED): the stage keeps a candidate for (a) by (a)'s score and stores the
    # candidate whose (b) scores best on the same held-out truths in directory/warm, (b)'s start.
    from ot_filter.amortised import load_map
    from ot_filter.experiments.amortised import (SELECTION_FOLD, amortised_updates, experiment_model, map_for,
                                                 selection_truths, warm_map_for, warm_options)

    small = dict(num_particles=40, num_iterations=60, num_simulations=3, num_steps=30)
    # (b) may start from the plain maps only (WARM_SELECTED): the layer map is not scored for (b)
    candidates = {"plain": {}, "plain_second_training": {"training_fold": 1}, "enkf_layer": {"enkf_layer": True}}
    directory = tmp_path / "lorenz63"
    kept, _ = map_for(str(directory), jax.random.key(3), "lorenz63", observed=(0,), workers=False,
                      candidates=candidates, gate=False, **small)  # the gate's own test is below
    assert "gate" not in kept.info["selection"]
    selection = kept.info["selection"]
    warm = selection["warm"]
    assert set(warm["scores"]) == {"plain", "plain_second_training"} and set(selection["scores"]) == set(candidates)
    warm_mse = {label: np.inf if score["mse"] is None else score["mse"] for label, score in warm["scores"].items()}
    assert warm["chosen"] == min(warm_mse, key=warm_mse.get)
    # (b)'s score recomputed: the bank's 3 held-out truths (a)'s 30 begin with, the filter
    # amortised_ot(map, **warm_options)
    model = experiment_model("lorenz63", observed=(0,))
    truth_model, skip = selection_truths("lorenz63", observed=(0,), num_steps=30)
    assert skip == 3  # 30 steps do not reach t = 1.5: the first tenth
    chosen_map = load_map(directory / "candidates" / warm["chosen"])
    again = score_map(jax.random.fold_in(jax.random.key(3), SELECTION_FOLD), model, chosen_map, num_simulations=3,
                      num_steps=30, num_particles=40, skip_steps=skip, truth_model=truth_model,
                      filter_options=warm_options(chosen_map, "lorenz63"))
    np.testing.assert_allclose(again.mse, warm["scores"][warm["chosen"]]["mse"], rtol=1e-4)
    a_on_the_same = score_map(jax.random.fold_in(jax.random.key(3), SELECTION_FOLD), model, chosen_map,
                              num_simulations=3, num_steps=30, num_particles=40, skip_steps=skip, truth_model=truth_model)
    assert again.mse != pytest.approx(a_on_the_same.mse, rel=1e-3)  # (b), not (a)
    # warm_map_for: the stored start, the candidate's networks; (b) is built from it
    start = warm_map_for(str(directory), kept)
    for got, want in zip(jax.tree.leaves(start.params), jax.tree.leaves(chosen_map.params)):
        np.testing.assert_array_equal(got, want)
    assert start.info["warm_selection"]["chosen"] == warm["chosen"]
    updates = amortised_updates(kept, "lorenz63", start)
    assert set(updates) == {"amortised", "amortised_warm"}
    # Without a stored start (the dynamic example; a stage before 0.2.12): the map kept for (a).
    assert warm_map_for(str(tmp_path / "elsewhere"), kept) is kept


@pytest.mark.long  # two small Lorenz-63 trainings and the online OT filter on the held-out truths, twice
def test_a_stage_whose_kept_map_misses_the_gate_trains_further_candidates_and_reselects(tmp_path):
    # The gate holds the kept map's (a) to a multiple of the online OT filter's MSE on the same
    # held-out truths. A gate no small map can pass (1e-3) trains one further wave (the plain
    # setting from fold 1), scores it on the same truths, keeps the best of both and warns; the
    # same candidates under a gate they pass are reloaded, and nothing is added.
    from ot_filter.amortised import load_map, score_filter
    from ot_filter.experiments.amortised import (SELECTION_FOLD, experiment_model, map_for, online_update,
                                                 selection_truths)

    small = dict(num_particles=40, num_iterations=60, num_simulations=3, num_steps=30)
    directory = tmp_path / "gated"
    with pytest.warns(UserWarning, match=r"after 2 further trainings \(gate 0.001\)"):
        kept, _ = map_for(str(directory), jax.random.key(3), "lorenz63", observed=(0,), workers=False,
                          candidates={"plain": {}}, gate=1e-3, extra_waves=2, selection_simulations=4, **small)
    selection = kept.info["selection"]
    gate = selection["gate"]
    assert gate["added"] == {"plain_training_1": {"training_fold": 1}, "plain_training_2": {"training_fold": 2}}
    assert set(selection["scores"]) == {"plain", "plain_training_1", "plain_training_2"}
    assert json.loads((directory / "candidates" / "plain_training_2" / "options.json").read_text())["training_fold"] == 2
    mse = {label: np.inf if score["mse"] is None else score["mse"] for label, score in selection["scores"].items()}
    assert selection["chosen"] == min(mse, key=mse.get)
    for got, want in zip(jax.tree.leaves(kept.params),
                         jax.tree.leaves(load_map(directory / "candidates" / selection["chosen"]).params)):
        np.testing.assert_array_equal(got, want)
    # the online filter's score recomputed: the held-out truths, the experiment's online OT update
    truth_model, skip = selection_truths("lorenz63", observed=(0,), num_steps=30)
    online = score_filter(jax.random.fold_in(jax.random.key(3), SELECTION_FOLD), experiment_model("lorenz63", observed=(0,)),
                          online_update("lorenz63"), num_simulations=4, num_steps=30, num_particles=40,
                          skip_steps=skip, truth_model=truth_model)
    np.testing.assert_allclose(gate["online"]["mse"], online.mse, rtol=1e-4)
    assert not gate["passed"] and gate["a_vs_online"] == pytest.approx(mse[selection["chosen"]] / online.mse, rel=1e-4)
    # (a) and the online filter on the 4 selection truths, (b)'s start among all three on the bank's 3
    assert {len(score["per_simulation"]) for score in selection["scores"].values()} == {4}
    assert len(gate["online"]["per_simulation"]) == 4
    warm = selection["warm"]
    assert set(warm["scores"]) == set(mse)
    assert {len(score["per_simulation"]) for score in warm["scores"].values()} == {3}
    # An interrupted stage resumes: the same gate reloads the further trainings, trains nothing, and
    # comes to the same choice.
    (directory / "map.json").unlink()
    stored = {label: os.path.getmtime(directory / "candidates" / label / "map.json") for label in mse}
    with pytest.warns(UserWarning, match="after 2 further trainings"):
        resumed, histories = map_for(str(directory), jax.random.key(3), "lorenz63", observed=(0,), workers=False,
                                     candidates={"plain": {}}, gate=1e-3, extra_waves=2, selection_simulations=4,
                                     **small)
    assert histories is None and resumed.info["selection"]["gate"]["added"] == gate["added"]
    assert resumed.info["selection"]["chosen"] == selection["chosen"]
    assert {label: os.path.getmtime(directory / "candidates" / label / "map.json") for label in mse} == stored
    # A gate the candidates pass: the stored candidates are reloaded, none is added.
    (directory / "map.json").unlink()
    again, histories = map_for(str(directory), jax.random.key(3), "lorenz63", observed=(0,), workers=False,
                               candidates={"plain": {}}, gate=1e6, selection_simulations=4, **small)
    assert histories is None  # reloaded, not trained
    assert again.info["selection"]["gate"]["added"] == {} and again.info["selection"]["gate"]["passed"]
    assert set(again.info["selection"]["scores"]) == {"plain"}
    np.testing.assert_allclose(again.info["selection"]["gate"]["online"]["mse"], online.mse, rtol=1e-4)


def _distilled(trained_map, width, num_iterations):
    model = scalar_model()
    bank = collect_forecasts(jax.random.key(11), model, otf.amortised_ot(trained_map), num_simulations=10,
                             num_steps=30, num_particles=200, burn_in=5)
    training, validation = split_bank(bank, 0.2)
    return distil_map(jax.random.key(12), trained_map, model, training, validation, width=width,
                      num_iterations=num_iterations, batch_size=256, ensembles_per_batch=8, chunks=2)


@pytest.mark.long
def test_a_map_distilled_into_narrower_networks_still_matches_the_kalman_filter(trained, tmp_path):
    # The teacher's test above with a student a quarter as wide, fitted by regression to the
    # teacher's T and f on its own filter's forecasts. An untrained student is the identity
    # (relative error 1: no conditioning) and fails the Kalman comparison by far.
    trained_map, _, _ = trained
    student, history = _distilled(trained_map, 8, 3000)
    assert student.config == trained_map.config._replace(width=8)
    assert student.info["distilled_from"]["width"] == 32 and student.info["finite"]
    assert history.transport_error[-1] < 0.1 and history.transport_error[-1] < history.transport_error[0]
    _assert_matches_kalman(otf.amortised_ot(student))
    # A student is a map like any other: it saves and reloads with its record.
    save_map(tmp_path / "student", student)
    again = load_map(tmp_path / "student", model="scalar-lg", state_dim=1)
    assert again.config.width == 8 and again.info["distilled_from"]["width"] == 32
    np.testing.assert_array_equal(jax.tree.leaves(again.params)[0], jax.tree.leaves(student.params)[0])


def test_distillation_checks_its_arguments(contextual):
    model = scalar_model()
    bank = collect_forecasts(jax.random.key(3), model, otf.enkf(), num_simulations=2, num_steps=4,
                                           num_particles=20)
    other = bank._replace(particles=jnp.zeros(bank.particles.shape[:2] + (2,)))
    with pytest.raises(ValueError, match="validation must be a ForecastBank"):
        distil_map(jax.random.key(0), contextual, model, bank, other, width=4)
    with pytest.raises(ValueError, match="batch_size"):
        distil_map(jax.random.key(0), contextual, model, bank, bank, width=4, batch_size=30, ensembles_per_batch=4)
    with pytest.raises(TypeError, match="teacher must be an AmortisedMap"):
        distil_map(jax.random.key(0), contextual.params, model, bank, bank, width=4)


def _rescaled(trained_map, shift, factor):
    """The same networks reading the context through another standardisation (as a training of
    the same setting on another bank would)."""
    scaling = trained_map.context_scaling
    return trained_map._replace(context_scaling=scaling._replace(mean=scaling.mean + shift, scale=scaling.scale * factor))


def test_the_average_of_several_teachers_reads_each_through_its_own_context_scaling(contextual):
    # Dense reference: each teacher's T and f on a batch built with its OWN context scaling (same
    # key: same pairs and observations), averaged. The distillation builds the batch once, with
    # the first teacher's scaling, and converts the context for the others.
    from ot_filter.amortised.distillation import _context_conversions, teacher_average

    model = scalar_model()
    bank = collect_forecasts(jax.random.key(3), model, otf.enkf(), num_simulations=3, num_steps=5, num_particles=50)
    first, second = contextual, _rescaled(contextual, 0.7, 2.5)
    structure = map_recipe(first.config, context_scaling=first.context_scaling)[1]

    def batch(one):
        return bank_batch(jax.random.key(4), bank, model.sample_observation, batch_size=32, ensembles_per_batch=4,
                          enkf_layer=False, context_scaling=one.context_scaling)

    own = [teacher_average((one.params,), None if one.context_scaling is None else _context_conversions((one,)),
                           batch(one), (structure,)) for one in (first, second)]
    assert float(jnp.max(jnp.abs(own[0][2] - own[1][2]))) > 1e-3  # the scalings change T: the check can fail
    inputs, y, target, f_target = teacher_average((first.params, second.params), _context_conversions((first, second)),
                                                  batch(first), (structure, structure))
    np.testing.assert_allclose(target, (own[0][2] + own[1][2]) / 2, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(y, own[0][1])
    potential = networks(structure)[0]
    points = jnp.concatenate([batch(first).x, target])
    expected = sum(potential.apply(one.params.potential, points, jnp.concatenate([b.y, b.y])) for one, b in
                   ((first, None), (second, None)) for b in [_with_context(batch(one))]) / 2
    np.testing.assert_allclose(f_target, expected, rtol=1e-5, atol=1e-6)


def _with_context(batch):
    """The batch's observations with its context appended (what the networks condition on)."""
    from ot_filter.transport.context import conditioning

    return batch._replace(y=conditioning(batch.y, batch.context))


def test_a_teacher_given_twice_distils_as_it_does_alone(contextual):
    model = scalar_model()
    bank = collect_forecasts(jax.random.key(3), model, otf.enkf(), num_simulations=4, num_steps=6, num_particles=40)
    training, validation = split_bank(bank, 0.25)
    options = dict(width=4, num_iterations=40, batch_size=32, ensembles_per_batch=4, chunks=2)
    alone, _ = distil_map(jax.random.key(5), contextual, model, training, validation, **options)
    twice, _ = distil_map(jax.random.key(5), [contextual, contextual], model, training, validation, **options)
    for got, want in zip(jax.tree.leaves(twice.params), jax.tree.leaves(alone.params)):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert [one["width"] for one in twice.info["distilled_from"]["teachers"]] == [8, 8]
    # The second teacher is read: another one (the same networks on another context scaling) moves the student.
    other, _ = distil_map(jax.random.key(5), [contextual, _rescaled(contextual, 0.7, 2.5)], model, training,
                          validation, **options)
    assert max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(other.params),
                                                              jax.tree.leaves(alone.params))) > 1e-4
    assert alone.info["distilled_from"]["width"] == 8


def test_distilling_several_teachers_checks_they_share_a_setting(contextual):
    model = scalar_model()
    bank = collect_forecasts(jax.random.key(3), model, otf.enkf(), num_simulations=2, num_steps=4, num_particles=20)
    other = contextual._replace(config=contextual.config._replace(inner_steps=3))
    with pytest.raises(ValueError, match=r"teacher\[1\] was trained .* other settings"):
        distil_map(jax.random.key(0), [contextual, other], model, bank, bank, width=4)
    with pytest.raises(TypeError, match="non-empty sequence"):
        distil_map(jax.random.key(0), [], model, bank, bank, width=4)
    # Widths may differ: a wider teacher beside a narrower one is accepted.
    from ot_filter.updates.ot import init_training

    config = contextual.config._replace(width=12)
    settings, structure = map_recipe(config, context_scaling=contextual.context_scaling)
    params = init_training(settings, structure, jax.random.key(2), 1, 1, jnp.float32).params
    wider = AmortisedMap(params, contextual.context_scaling, config, {})
    student, _ = distil_map(jax.random.key(0), [contextual, wider], model, bank, bank, width=4, num_iterations=4,
                            batch_size=16, ensembles_per_batch=4, chunks=1)
    assert student.config.width == 4 and student.info["finite"]


def test_the_candidates_of_the_kept_maps_setting_are_the_distillations_teachers(contextual, tmp_path):
    from ot_filter.experiments.amortised import distilled_width, same_setting_candidates

    assert same_setting_candidates(str(tmp_path), contextual) == [contextual]  # no candidates stored
    save_map(tmp_path / "candidates" / "plain", contextual)
    assert same_setting_candidates(str(tmp_path), contextual) == [contextual]  # one: nothing to average
    again = _rescaled(contextual, 0.1, 1.5)
    save_map(tmp_path / "candidates" / "plain_second_training", again)
    save_map(tmp_path / "candidates" / "enkf_layer", contextual._replace(config=contextual.config._replace(enkf_layer=True)))
    found = same_setting_candidates(str(tmp_path), contextual)  # no selection record: every one of the setting
    assert len(found) == 2 and all(one.config == contextual.config for one in found)
    np.testing.assert_allclose(found[1].context_scaling.mean, again.context_scaling.mean)
    assert distilled_width(2, 64) == distilled_width(3, 64) == 16 and distilled_width(10, 64) == 64

    def kept(second, chosen="plain", scored=("plain", "plain_second_training")):
        scores = {"plain": {"mse": 1.0, "stderr": 0.1, "per_simulation": [0.9, 1.0, 1.1]},
                  "plain_second_training": {"mse": None if None in second else float(np.mean(second)),
                                            "stderr": 0.1, "per_simulation": second}}
        scores = {label: scores[label] for label in scored}
        return contextual._replace(info=dict(contextual.info, selection={"chosen": chosen, "scores": scores}))

    assert len(same_setting_candidates(str(tmp_path), kept([0.95, 1.1, 1.1]))) == 2
    # The kept candidate first (its context scaling is the student's).
    first = same_setting_candidates(str(tmp_path), kept([0.95, 1.1, 1.1], chosen="plain_second_training"))[0]
    np.testing.assert_allclose(first.context_scaling.mean, again.context_scaling.mean)
    # Left out: a candidate the held-out selection found worse, one it could not score (None: not
    # finite) and one it did not score at all.
    for record in (kept([1.9, 2.0, 2.1]), kept([0.9, None, 1.1]), kept([0.9, 1.0, 1.1], scored=("plain",))):
        assert same_setting_candidates(str(tmp_path), record) == [record]
