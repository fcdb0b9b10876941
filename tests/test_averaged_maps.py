"""averaged_maps: K trainings of a map, their outputs averaged (the members left out where they
fell back), against the members run one by one."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.experiments._common import diverged_flags, make_updates, methods_present
from ot_filter.updates.base import uniform_log_weights

STATIC = otf.models.squared_observation(dim=2, noise=0.4, observation_scale=0.5, static=True)


class _ShiftState(NamedTuple):
    log_weights: jax.Array
    shift: jax.Array
    diverged: jax.Array


class _ShiftInfo(NamedTuple):
    diverged: jax.Array


class _Shift(NamedTuple):
    init: object
    apply: object
    transport: object


def _shift_update(threshold):
    """A stand-in map: moves every particle by a shift drawn from its init key; it 'diverges'
    (falls back to moving by 100 + shift) where the shift is above ``threshold``."""
    def init(key, particles, model=None):
        return _ShiftState(uniform_log_weights(particles), jax.random.normal(key), jnp.asarray(False))

    def apply(key, state, particles, observation, model):
        diverged = state.shift > threshold
        moved = particles + jnp.where(diverged, 100.0 + state.shift, state.shift)  # each its own fallback
        return moved, state._replace(diverged=diverged), _ShiftInfo(diverged)

    def transport(state, particles, observation):
        return particles + state.shift

    return _Shift(init, apply, transport)


@pytest.mark.parametrize("threshold", [10.0, 0.0, -10.0])
def test_the_average_leaves_out_the_members_that_fell_back(threshold):
    particles = jnp.arange(6.0).reshape(3, 2)
    update = otf.averaged_maps(_shift_update(threshold), 4)
    state = update.init(jax.random.key(0), particles)
    shifts = np.asarray(state.maps.shift)
    assert len(set(shifts.round(6))) == 4  # every member has its own key
    moved, state, info = update.apply(jax.random.key(1), state, particles, jnp.zeros(2), None)
    used = shifts <= threshold
    if threshold == 0.0:  # key 0's four shifts fall on both sides: the mixed case is tested
        assert 0 < used.sum() < 4
    if used.any():
        expected = np.asarray(particles) + shifts[used].mean()
    else:  # every member fell back: the first member's fallback, not an average of fallbacks
        expected = np.asarray(particles) + 100.0 + shifts[0]
    np.testing.assert_allclose(moved, expected, rtol=1e-6)
    assert int(info.num_averaged) == used.sum() and bool(info.diverged) == (not used.any())
    np.testing.assert_array_equal(info.maps.diverged, ~used)
    assert bool(diverged_flags(info)) == (not used.any())  # the experiments count whole fallbacks
    # transport averages the same members (the first member's map when all fell back)
    mapped = np.asarray(particles) + (shifts[used].mean() if used.any() else shifts[0])
    np.testing.assert_allclose(update.transport(state, particles, jnp.zeros(2)), mapped, rtol=1e-6)


def test_averaged_ot_is_the_mean_of_its_members_trained_one_by_one():
    member = otf.ot(num_iterations=40, concavity_points=0)
    update = otf.averaged_maps(member, 3)
    particles = jax.random.normal(jax.random.key(0), (64, 2))
    y = jnp.array([1.0, 0.5])
    init_key, apply_key = jax.random.key(1), jax.random.key(2)
    state = update.init(init_key, particles, STATIC)
    moved, state, info = jax.jit(update.apply)(apply_key, state, particles, y, STATIC)

    alone = []
    for one_init, one_apply in zip(jax.random.split(init_key, 3), jax.random.split(apply_key, 3)):
        one_state = member.init(one_init, particles, STATIC)
        alone.append(jax.jit(member.apply)(one_apply, one_state, particles, y, STATIC)[0])
    alone = np.stack(alone)
    assert not np.any(np.asarray(info.maps.diverged)) and int(info.num_averaged) == 3
    assert np.abs(alone[0] - alone[1]).max() > 1e-3  # the members differ: the average is not one of them
    np.testing.assert_allclose(moved, alone.mean(0), rtol=1e-4, atol=1e-5)
    # The conditional map: transport at the same y reproduces apply; at another y it is the
    # average of the members' maps there.
    np.testing.assert_allclose(update.transport(state, particles, y), moved, rtol=1e-4, atol=1e-5)
    other = jnp.array([0.2, 2.0])
    members = [member.transport(jax.tree.map(lambda leaf: leaf[k], state.maps), particles, other) for k in range(3)]
    np.testing.assert_allclose(update.transport(state, particles, other), np.mean(members, 0), rtol=1e-4, atol=1e-5)
    # jit and no jit agree
    eager, _, _ = update.apply(apply_key, update.init(init_key, particles, STATIC), particles, y, STATIC)
    np.testing.assert_allclose(eager, moved, rtol=1e-4, atol=1e-5)


@pytest.mark.long
def test_averaged_maps_runs_in_a_filter_vmapped_over_a_setting_in_one_program():
    model = otf.models.squared_observation(dim=2, noise=0.4, observation_scale=0.5)
    _, observations = otf.simulate(jax.random.key(0), model, 4)

    def run(rate):
        update = otf.averaged_maps(otf.ot(num_iterations=(16, 8), transport_learning_rate=rate, concavity_points=0), 2)
        return otf.run_filter(jax.random.key(1), model, update, observations, 32, save_every=0).mean

    rates = jnp.asarray([1e-3, 3e-3])
    swept = jax.jit(jax.vmap(run))(rates)
    assert swept.shape == (2, 4, 2) and np.all(np.isfinite(swept))
    np.testing.assert_allclose(swept[1], jax.jit(run)(rates[1]), rtol=1e-4, atol=1e-5)
    assert not np.allclose(swept[0], swept[1])


def test_averaged_maps_refuses_what_it_cannot_average():
    with pytest.raises(ValueError, match="num_maps"):
        otf.averaged_maps(otf.ot(), 0)
    with pytest.raises(TypeError, match="update must be a map-based"):
        otf.averaged_maps(otf.enkf(), 2)  # the average of K EnKF outputs is not a posterior draw
    with pytest.raises(TypeError, match="averaged already"):
        otf.averaged_maps(otf.averaged_maps(otf.ot(), 2), 2)
    with pytest.raises(ValueError, match="perturbed EnKF layer"):  # it would shrink the perturbations
        otf.averaged_maps(otf.ot(enkf_layer=True), 2)
    otf.averaged_maps(otf.ot(enkf_layer="deterministic"), 2)  # a map: accepted
    with pytest.raises(ValueError, match="ot_avgK"):
        make_updates(["enkf_avg2"], None)
    assert methods_present(["local_ot_avg3", "ot", "enkf", "unknown"]) == ["enkf", "ot", "local_ot_avg3"]
    updates = make_updates(["ot_avg2", "local_ot_avg3"], None, model=STATIC, radius=0.0)
    particles = jnp.zeros((8, 2))
    for name, base, count in (("ot_avg2", "ot_apply", 2), ("local_ot_avg3", "local_ot_apply", 3)):
        assert isinstance(updates[name], otf.updates.AveragedMapsUpdate)
        member = updates[name].apply.args[0]  # each name its own base method and count
        assert member.apply.func.func.__name__ == base
        assert updates[name].init(jax.random.key(0), particles, STATIC).maps.log_weights.shape == (count, 8)


@pytest.mark.long
def test_averaged_local_maps_in_a_padded_filter_and_their_transport():
    model = otf.models.squared_observation(dim=3, noise=0.4, observation_scale=0.5)
    _, observations = otf.simulate(jax.random.key(0), model, 3)
    windows = otf.local_windows(model.geometry, 0.0)
    update = otf.averaged_maps(otf.local_ot(windows, num_iterations=(16, 8)), 2)
    result = otf.run_filter(jax.random.key(1), model, update, observations, 24, num_active=16, save_every=1)
    assert np.all(np.isfinite(result.mean))
    np.testing.assert_array_equal(np.isneginf(result.final_state.log_weights), np.arange(24) >= 16)
    np.testing.assert_array_equal(np.isneginf(result.final_state.maps.log_weights),
                                  np.broadcast_to(np.arange(24) >= 16, (2, 24)))
    # transport forwards local_ot's model argument and averages the members' maps
    prior, y = jax.random.normal(jax.random.key(2), (16, 3)), observations[0]
    state = update.init(jax.random.key(3), prior, model)
    moved, state, info = update.apply(jax.random.key(4), state, prior, y, model)
    assert int(info.num_averaged) == 2
    np.testing.assert_allclose(update.transport(state, prior, y, model), moved, rtol=1e-4, atol=1e-5)
