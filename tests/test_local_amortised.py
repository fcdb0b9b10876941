"""The localised OT update with an offline-trained shared map (``amortised.local``,
``local_ot(initial_map=...)``)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.amortised.local import local_bank, local_bank_batch, train_local_map
from ot_filter.localisation import local_windows, taper_support
from ot_filter.transport.saddle import SaddleParams


def _tree_equal(a, b):
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_an_untrained_map_used_as_is_is_the_letkf_and_stays_as_given(x64):
    """T's last layer starts at zero: an initial map straight from ``init`` moves every particle to
    the deterministic layer's output, the tapered LETKF; with no iterations nothing trains, and
    the state holds the given parameters, not a random draw."""
    model = otf.models.lorenz96(dim=12, observed=np.arange(0, 12, 2))
    prior = 3.0 + 2.0 * jax.random.normal(jax.random.PRNGKey(0), (40, 12))
    observation = jax.vmap(model.observation_function)(prior[:1])[0] + 0.5
    radius = 4.5
    options = dict(enkf_layer="deterministic", taper="gaspari_cohn", inflation=1.1)
    windows = local_windows(model.geometry, radius)
    given = otf.local_ot(windows, num_iterations=1, **options).init(jax.random.PRNGKey(5), prior, model).training.params
    update = otf.local_ot(windows, num_iterations=0, initial_map=given, **options)
    state = update.init(jax.random.PRNGKey(1), prior, model)
    assert _tree_equal(state.training.params, given)  # another key would draw other parameters
    posterior, state, info = update.apply(jax.random.PRNGKey(2), state, prior, observation, model)
    assert not bool(info.diverged)
    assert _tree_equal(state.training.params, given)
    assert info.loss.shape == (0,)
    letkf = otf.letkf(otf.localisation(model.geometry, radius / taper_support(1.0, "gaspari_cohn"),
                                       taper="gaspari_cohn"), inflation=1.1)
    expected, _, _ = letkf.apply(jax.random.PRNGKey(3), letkf.init(jax.random.PRNGKey(3), prior, model),
                                 prior, observation, model)
    np.testing.assert_allclose(posterior, expected, rtol=1e-8, atol=1e-8)


def test_a_map_of_other_sizes_is_refused():
    model = otf.models.lorenz96(dim=8)
    prior = jax.random.normal(jax.random.PRNGKey(0), (20, 8))
    windows = local_windows(model.geometry, 1.0)
    narrow = otf.local_ot(windows, width=16).init(jax.random.PRNGKey(0), prior, model).training.params
    with pytest.raises(ValueError, match="initial_map does not fit"):
        otf.local_ot(windows, width=32, num_iterations=0, initial_map=narrow).init(jax.random.PRNGKey(0), prior, model)
    with pytest.raises(TypeError, match="initial_map must be a SaddleParams"):
        otf.local_ot(windows, initial_map={"potential": None})
    with pytest.raises(ValueError, match="num_iterations must be a positive int"):
        otf.local_ot(windows, num_iterations=0)  # 0 iterations needs a map to use
    with pytest.raises(ValueError, match="the bank stores each pair's simulated observations"):
        local_bank(jax.random.PRNGKey(0), otf.local_ot(windows, fresh_observations=True), model, prior[None])


def test_bank_batches_pair_a_copy_of_the_same_ensemble_and_coordinate():
    """Each row: a pair (x, y) of one (ensemble, particle, coordinate), its independent copy from
    the same ensemble and coordinate (another particle drawn), and that window's gain."""
    model = otf.models.lorenz96(dim=6)
    update = otf.local_ot(local_windows(model.geometry, 1.0), enkf_layer="deterministic")
    forecasts = 10.0 * jnp.arange(3.0)[:, None, None] + jax.random.normal(jax.random.PRNGKey(0), (3, 30, 6))
    bank = local_bank(jax.random.PRNGKey(1), update, model, forecasts)
    assert bank.x.shape[:3] == (3, 30, 6) and bank.gain.shape[:2] == (3, 6)
    batch = local_bank_batch(jax.random.PRNGKey(2), bank, 64, True)
    assert batch.x.shape == (64, bank.x.shape[-1]) and batch.gain.shape == (64,) + bank.gain.shape[2:]

    def where(table, rows):  # (ensemble, particle, coordinate) of each row, found by value
        flat = np.asarray(table).reshape(-1, table.shape[-1])
        found = [np.flatnonzero(np.all(flat == row, axis=1)) for row in np.asarray(rows)]
        assert all(len(f) == 1 for f in found)  # continuous draws: every window is unique
        return np.stack(np.unravel_index(np.concatenate(found), table.shape[:3]), axis=1)

    pair, copy = where(bank.x, batch.x), where(bank.layer_x, batch.xbar)
    np.testing.assert_array_equal(where(bank.y, batch.y), pair)  # y is x's own observation
    np.testing.assert_array_equal(pair[:, [0, 2]], copy[:, [0, 2]])  # same ensemble and coordinate
    assert len(np.unique(pair[:, 0])) == 3 and np.mean(pair[:, 1] != copy[:, 1]) > 0.8  # mixed; other particles
    np.testing.assert_array_equal(batch.gain, np.asarray(bank.gain)[pair[:, 0], pair[:, 2]])


def test_an_offline_local_map_learns_the_gaussian_posterior():
    """Independent N(0, 1) coordinates, each observed with N(0, 1) noise, no layer: the shared
    map trained on a bank of prior ensembles must move a fresh prior to the exact posterior,
    N(y / 2, 1 / 2), with no training online (an untrained map would leave it at N(0, 1))."""
    dim, num = 8, 200
    model = otf.models.lorenz96(dim=dim, observation_noise_std=1.0)
    windows = local_windows(model.geometry, 0.0)
    template = otf.local_ot(windows, batch_size=256, potential_learning_rate=3e-4, prior_context=0)
    forecasts = jax.random.normal(jax.random.PRNGKey(0), (16, num, dim))
    bank = local_bank(jax.random.PRNGKey(1), template, model, forecasts)
    params, trace = train_local_map(jax.random.PRNGKey(2), template, bank, 3000)
    assert isinstance(params, SaddleParams) and bool(trace.finite)
    update = otf.local_ot(windows, num_iterations=0, initial_map=params, prior_context=0)
    prior = jax.random.normal(jax.random.PRNGKey(3), (1000, dim))
    observation = jnp.ones(dim)
    posterior, _, info = update.apply(jax.random.PRNGKey(4), update.init(jax.random.PRNGKey(5), prior, model),
                                      prior, observation, model)
    assert not bool(info.diverged)
    # The exact map moves each particle to 1/2 + x / sqrt(2) (the Gaussian OT map). Compared on
    # the same particles, so no sampling error enters; what remains is the map's own. Measured
    # over three training seeds: at most 0.055 on a coordinate's mean, 0.056 on its spread,
    # 0.078 per particle (root mean square). Untrained (the identity): 0.5, 0.29 and 0.58.
    exact = 0.5 + np.sqrt(0.5) * np.asarray(prior)
    moved = np.asarray(posterior)
    np.testing.assert_allclose(moved.mean(axis=0), exact.mean(axis=0), atol=0.08)
    np.testing.assert_allclose(moved.std(axis=0), exact.std(axis=0), atol=0.08)
    assert np.sqrt(np.mean((moved - exact) ** 2)) < 0.12


def test_a_stored_local_map_reloads_bit_identically_filters_identically_and_refuses_another_model(tmp_path):
    """``train_local_amortised`` (chunks, held-out validation), ``save_local_map`` and
    ``load_local_map``: the reloaded parameters are the same bytes, the filter from them gives
    the same particles, and a map asked for as another model, or as a global map, is refused."""
    from ot_filter.amortised import (LocalMapConfig, MapMismatchError, amortised_local_ot, load_local_map, load_map,
                                     save_local_map, train_local_amortised)

    dim = 6
    model = otf.models.lorenz96(dim=dim, observation_noise_std=1.0)
    config = LocalMapConfig("ring-6", dim, dim, radius=1.0, width=16, batch_size=64)
    forecasts = jax.random.normal(jax.random.PRNGKey(0), (10, 30, dim))
    trained, history = train_local_amortised(jax.random.PRNGKey(1), model, config, forecasts, 40, chunks=4)
    np.testing.assert_array_equal(history.iterations, [10, 20, 30, 40])
    assert np.all(np.isfinite(history.validation_loss)) and history.validation_loss.shape == (4,)
    assert trained.info["ensembles"] == 8 and trained.info["validation_ensembles"] == 2
    # the validation J is the map's own: a different map has a different one
    assert len(np.unique(history.validation_loss)) == 4
    save_local_map(tmp_path / "map", trained)
    loaded = load_local_map(tmp_path / "map", model="ring-6", state_dim=dim)
    assert loaded.config == config and loaded.info == json.loads(json.dumps(trained.info))
    for got, want in zip(jax.tree.leaves(loaded.params), jax.tree.leaves(trained.params)):
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
    observations = otf.simulate(jax.random.PRNGKey(2), model, 4)[1]
    runs = [otf.run_filter(jax.random.PRNGKey(3), model, amortised_local_ot(one, model, iterations, batch_size=32),
                           observations, 30)
            for one in (trained, loaded) for iterations in (0, 3)]
    np.testing.assert_array_equal(runs[0].particles, runs[2].particles)  # (a) from either
    np.testing.assert_array_equal(runs[1].particles, runs[3].particles)  # (b) from either
    assert not np.array_equal(runs[0].particles, runs[1].particles)  # (b) trained online
    with pytest.raises(MapMismatchError, match="asked for model 'ring-8'"):
        load_local_map(tmp_path / "map", model="ring-8")
    with pytest.raises(MapMismatchError, match="asked for state_dim 8"):
        load_local_map(tmp_path / "map", state_dim=8)
    with pytest.raises(MapMismatchError, match="is a local map"):
        load_map(tmp_path / "map")
    with pytest.raises(ValueError, match="initial_map does not fit"):  # windows of another radius
        amortised_local_ot(loaded._replace(config=config._replace(radius=2.0)), model).init(
            jax.random.PRNGKey(0), forecasts[0], model)
    with pytest.raises(ValueError, match=r"\[.width.\] are the map.s"):
        amortised_local_ot(loaded, model, width=32)
    payload = (tmp_path / "map" / "params.msgpack").read_bytes()
    (tmp_path / "map" / "params.msgpack").write_bytes(payload[:-1] + bytes([payload[-1] ^ 1]))
    with pytest.raises(MapMismatchError, match="does not match the SHA-256"):
        load_local_map(tmp_path / "map")


def test_the_dynamic_examples_bank_grows_to_about_4000_local_problems():
    from ot_filter.experiments.local_amortised import bank_simulations

    # training ensembles (four fifths of simulations x steps) times n: at least 4,000 where the
    # cap allows, and at least 400 ensembles
    assert [bank_simulations(dim, 20) for dim in (2, 10, 50, 500)] == [60, 25, 25, 25]
    assert bank_simulations(2, 100) == 25 and bank_simulations(10, 10) == 50
    for dim in (10, 50):
        assert bank_simulations(dim, 20) * 20 * 0.8 * dim >= 4000
