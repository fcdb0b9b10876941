"""Saving and loading an amortised OT map: flax's msgpack serialisation of the parameters and a
JSON record of what the map is and how it was trained.

A map is a directory holding ``params.msgpack`` (``flax.serialization.to_bytes``: the arrays'
bytes exactly, so a reloaded map is bit-identical; an averaged map's last iterate with them)
and ``map.json`` (the ``MapConfig``, the
training info, the versions of ot_filter / jax / flax it was written with, and the parameters'
SHA-256). ``load_map(path, model=..., state_dim=..., observation_dim=...)`` refuses a map
trained for another model or other dimensions, and a parameter file that does not match its
record.

A local map (``amortised.local``: the localised update's shared networks) is stored the same
way by ``save_local_map`` (its ``LocalMapConfig`` as the config, ``"kind": "local"``) and read by
``load_local_map``; each loader refuses the other kind.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import flax
import jax
import jax.numpy as jnp
from flax import serialization

from ot_filter.amortised.local import LocalMap, LocalMapConfig
from ot_filter.amortised.training import AmortisedMap, MapConfig, map_recipe
from ot_filter.transport.context import ContextScaling
from ot_filter.transport.saddle import SaddleParams
from ot_filter.updates.ot import init_training

__all__ = ["MapMismatchError", "load_local_map", "load_map", "save_local_map", "save_map"]

PARAMS_FILE = "params.msgpack"
RECORD_FILE = "map.json"
FORMAT = 1


class MapMismatchError(ValueError):
    """A stored map was trained for another model, other dimensions, or its files disagree."""


def _package_version() -> str:
    """The version of the code that trained the map (as the runner's config.json records it):
    an editable installation's metadata keeps the version it was installed at."""
    from ot_filter import __version__  # here: the package imports this module

    return __version__


def save_map(path: str | os.PathLike, trained_map: AmortisedMap) -> Path:
    """Writes the map to the directory ``path`` (created; files replaced atomically)."""
    return _write(path, _stored(trained_map), "global", trained_map.config, trained_map.info, trained_map.params,
                  last_iterate=trained_map.last_iterate is not None)


def save_local_map(path: str | os.PathLike, local_map: LocalMap) -> Path:
    """Writes a local map (``amortised.local``) to the directory ``path``."""
    return _write(path, local_map.params, "local", local_map.config, local_map.info, local_map.params)


def _write(path, arrays, kind: str, config, info: dict, params, **extra) -> Path:
    directory = Path(path)
    directory.mkdir(parents=True, exist_ok=True)
    payload = serialization.to_bytes(jax.device_get(arrays))
    record = {
        "format": FORMAT,
        "kind": kind,
        "config": config._asdict(),
        "info": info,
        "dtype": str(jax.tree.leaves(params)[0].dtype),
        **extra,
        "sha256": hashlib.sha256(payload).hexdigest(),
        "versions": {"ot_filter": _package_version(), "jax": jax.__version__, "flax": flax.__version__},
    }
    _write_atomic(directory / PARAMS_FILE, payload)
    _write_atomic(directory / RECORD_FILE, json.dumps(record, indent=2, default=float).encode())
    return directory


def load_map(path: str | os.PathLike, *, model: str | None = None, state_dim: int | None = None,
             observation_dim: int | None = None) -> AmortisedMap:
    """Reads a map written by ``save_map``; each of ``model``, ``state_dim``, ``observation_dim``
    that is given must be what the map was trained for (else ``MapMismatchError``)."""
    directory, record, payload, config = _read(path, "global", MapConfig, model=model, state_dim=state_dim,
                                               observation_dim=observation_dim)
    settings, structure = map_recipe(config)
    dtype = jnp.dtype(record["dtype"])
    params = init_training(settings, structure, jax.random.key(0), config.state_dim, config.observation_dim,
                           dtype).params
    template = AmortisedMap(
        params,
        None if settings.context_scaling is None else jax.tree.map(lambda a: a.astype(dtype), settings.context_scaling),
        config, {}, params if record.get("last_iterate", False) else None,  # maps of 0.2.6 have none
    )
    stored = serialization.from_bytes(_stored(template), payload)
    return AmortisedMap(jax.tree.map(jnp.asarray, stored["params"]),
                        None if stored["context_scaling"] is None else ContextScaling(
                            *(jnp.asarray(stored["context_scaling"][k]) for k in ("mean", "scale"))),
                        config, record["info"],
                        None if template.last_iterate is None else jax.tree.map(jnp.asarray, stored["last_iterate"]))


def load_local_map(path: str | os.PathLike, *, model: str | None = None, state_dim: int | None = None,
                   observation_dim: int | None = None) -> LocalMap:
    """Reads a local map written by ``save_local_map`` (checked as ``load_map`` checks). The
    networks' shapes are checked against the windows when the map is used
    (``amortised_local_ot``)."""
    _, record, payload, config = _read(path, "local", LocalMapConfig, model=model, state_dim=state_dim,
                                       observation_dim=observation_dim)
    stored = serialization.msgpack_restore(payload)
    as_arrays = lambda tree: jax.tree.map(jnp.asarray, tree)  # noqa: E731
    return LocalMap(SaddleParams(as_arrays(stored["potential"]), as_arrays(stored["transport"])), config,
                    record["info"])


def _read(path, kind: str, config_type, **asked):
    """``(directory, record, payload, config)`` of a stored map of ``kind``, each ``asked``
    value that is not None checked against its config, the payload against its SHA-256."""
    directory = Path(path)
    try:
        record = json.loads((directory / RECORD_FILE).read_text())
        payload = (directory / PARAMS_FILE).read_bytes()
    except FileNotFoundError as error:
        raise FileNotFoundError(f"no amortised map at {directory} ({error.filename} missing)") from None
    if record.get("format") != FORMAT:
        raise MapMismatchError(f"{directory}: map format {record.get('format')!r}, this version reads {FORMAT}")
    stored_kind = record.get("kind", "global")  # maps written before local ones are global
    if stored_kind != kind:
        loader = "load_local_map" if stored_kind == "local" else "load_map"
        raise MapMismatchError(f"the map at {directory} is a {stored_kind} map, not a {kind} one: read it with {loader}")
    config = config_type(**record["config"])
    wrong = {name: value for name, value in asked.items()
             if value is not None and value != getattr(config, name)}
    if wrong:
        raise MapMismatchError(
            f"the map at {directory} was trained for model {config.model!r} (state dimension "
            f"{config.state_dim}, observation dimension {config.observation_dim}); asked for "
            + ", ".join(f"{name} {value!r}" for name, value in wrong.items())
        )
    if hashlib.sha256(payload).hexdigest() != record["sha256"]:
        raise MapMismatchError(f"{directory}: {PARAMS_FILE} does not match the SHA-256 in {RECORD_FILE}")
    return directory, record, payload, config


def _stored(trained_map: AmortisedMap) -> dict:
    """The arrays of a map, as serialised."""
    scaling = trained_map.context_scaling
    stored = {"params": trained_map.params,
              "context_scaling": None if scaling is None else {"mean": scaling.mean, "scale": scaling.scale}}
    if trained_map.last_iterate is not None:  # absent, not None: maps without it read as before
        stored["last_iterate"] = trained_map.last_iterate
    return stored


def _write_atomic(path: Path, data: bytes) -> None:
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_bytes(data)
    os.replace(temporary, path)
