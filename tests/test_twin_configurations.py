"""DAPPER's twin configurations (ot_filter.experiments.twin_configurations): each builds, its
update filters its model's truth, overrides reach the update, names are unique."""

import functools

import jax
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.experiments import TWIN_CONFIGURATIONS, TWIN_EXPERIMENTS, twin_model

NUM_CYCLES = 20


@functools.lru_cache(maxsize=None)
def truth(model_name):
    """(model, states, observations) of a 20-cycle truth, one per model (compiled once)."""
    model = twin_model(model_name)
    return (model, *otf.simulate(jax.random.key(0), model, NUM_CYCLES))


@pytest.mark.parametrize("name", sorted(TWIN_CONFIGURATIONS))
def test_configuration_builds_and_filters(name):
    config = TWIN_CONFIGURATIONS[name]
    assert config.name == name and config.model_name in TWIN_EXPERIMENTS
    assert config.dapper_method.split("(")[0] in ("EnKF", "PartFilt")
    assert f"N={config.num_particles}" in config.dapper_method
    model, states, observations = truth(config.model_name)
    result = otf.run_filter(jax.random.key(1), model, config.build_update(), observations,
                            config.num_particles, save_every=0)
    assert result.mean.shape == states.shape
    assert np.all(np.isfinite(np.asarray(result.mean)))


def spied(config):
    """The configuration with its update factory recording the settings it is called with."""
    seen, factory = [], config.update_factory

    def spy(**settings):
        seen.append(settings)
        return factory(**settings)

    return config._replace(update_factory=spy), seen


def test_overrides_reach_the_update():
    config, seen = spied(TWIN_CONFIGURATIONS["L63/EnKF-Sqrt-N10"])
    config.build_update()
    config.build_update(inflation=1.05)
    assert seen == [{"inflation": 1.02}, {"inflation": 1.05}]
    with pytest.raises(TypeError, match="unknown settings"):
        config.build_update(jitter=0.5)
    with pytest.raises(ValueError, match="inflation"):  # the number reaches ot_filter.enkf
        config.build_update(inflation=0.5)
    config, seen = spied(TWIN_CONFIGURATIONS["L63/PartFilt-N800"])
    config.build_update(jitter=0.5)
    assert seen == [{"ess_threshold": 0.2, "jitter": 0.5}]


def test_names_unique_and_conventions():
    configs = list(TWIN_CONFIGURATIONS.values())
    assert len({c.name for c in configs}) == len(configs)
    assert len({c.label for c in configs}) == len(configs)
    assert {c.model_name for c in configs} == set(TWIN_EXPERIMENTS)
    for experiment in TWIN_EXPERIMENTS.values():  # DAPPER's averaging window (Ko = 1000)
        assert experiment.num_analyses - experiment.burn_in == experiment.analyses_averaged
    assert TWIN_EXPERIMENTS["lorenz63"].burn_in == 64 and TWIN_EXPERIMENTS["lorenz96"].burn_in == 400
    with pytest.raises(ValueError, match="unknown twin model"):
        twin_model("lorenz84")
