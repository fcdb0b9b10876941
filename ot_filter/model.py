"""State-space models as pytrees of pure per-particle functions, and their simulation.

A discrete-time model (the chapter's eq. model-dyn-discrete / model-obs-discrete) is

    X_0 ~ pi_0,    X_t ~ a(. | X_{t-1}),    Y_t ~ h(. | X_t),    t = 1, 2, ...

and is given to the library as functions of ONE state (``x[n]``); the library vmaps them over
particles. Only the simulator is required (the chapter's "simulation-based" setting, enough for
EnKF and OT); ``log_likelihood`` adds the "analytical" setting that SIR needs. Models with
additive Gaussian observation noise ``Y = h(X) + V, V ~ N(0, R)`` may also give ``h`` and ``R``,
which the EnKF then uses exactly, and from which the OT updates simulate their ensembles'
observations (``simulate_observations``): ``sample_observation`` must then draw the same law.

``StateSpaceModel`` is a pytree: its functions are static (part of the tree structure, compared
by identity) and its arrays (``observation_noise_cov``, ``parameters``) are leaves, so a model
can be passed straight into ``jax.jit``-compiled functions. The built-in models bind module-level
functions to their numbers with ``lib.static.bind``: those numbers are leaves too, and two models
built with the same structure share the compiled programs (no cache of model objects needed). The built-in models' functions
close over their own parameters: treat the leaves as read-only descriptions of them
(``model._replace(observation_noise_cov=R2)`` changes what the EnKF and the OT updates use, not
``sample_observation``);
build a new model to change a parameter.
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

__all__ = ["StateSpaceModel", "colour_noise", "dense_noise_cov", "model_dimensions", "observation_noise", "simulate",
           "simulate_observations", "whiten"]


def check_covariance(name: str, matrix, size: int, positive_definite: bool,
                     allow_diagonal: bool = False) -> None:
    """Raises ValueError (naming ``name``) unless ``matrix`` is a finite symmetric [size, size]
    positive (semi-)definite matrix, or a diagonal ``[size]`` of positive (non-negative) entries.
    Traced values (inside jit / vmap) are only shape-checked."""
    if np.ndim(matrix) == 1 and allow_diagonal:
        if np.shape(matrix) != (size,):
            raise ValueError(f"{name} must have shape ({size},) or ({size}, {size}), got {np.shape(matrix)}")
        if isinstance(matrix, jax.core.Tracer):
            return
        diagonal = np.asarray(matrix, dtype=np.float64)
        if not np.all(np.isfinite(diagonal)):
            raise ValueError(f"{name} must be finite")
        if (diagonal.min() <= 0) if positive_definite else (diagonal.min() < 0):
            raise ValueError(f"{name} (a diagonal) must be positive, smallest entry {diagonal.min():.3g}")
        return
    if np.shape(matrix) != (size, size):
        raise ValueError(f"{name} must have shape ({size}, {size}), got {np.shape(matrix)}")
    if isinstance(matrix, jax.core.Tracer):
        return
    matrix = np.asarray(matrix, dtype=np.float64)
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{name} must be finite")
    scale = max(1.0, float(np.abs(matrix).max()))
    if not np.allclose(matrix, matrix.T, rtol=1e-6, atol=1e-10 * scale):
        raise ValueError(f"{name} must be symmetric")
    smallest = float(np.linalg.eigvalsh(matrix).min())
    if positive_definite and smallest <= 0:
        raise ValueError(f"{name} must be positive definite (smallest eigenvalue {smallest:.3g})")
    if smallest < -1e-8 * scale:
        raise ValueError(f"{name} must be positive semi-definite (smallest eigenvalue {smallest:.3g})")


class StateSpaceModel(NamedTuple):
    """A discrete-time state-space model given by per-particle functions.

    Attributes:
      sample_initial: ``key -> x[n]``, a draw from pi_0.
      sample_transition: ``(key, x[n]) -> x[n]``, a draw from a(. | x).
      sample_observation: ``(key, x[n]) -> y[m]``, a draw from h(. | x).
      log_likelihood: optional ``(y[m], x[n]) -> scalar``, the log density log l(y | x)
        (needed by SIR; keep its normalising constant if you want SIR's marginal likelihood).
      observation_function: optional noiseless ``x[n] -> h(x)[m]`` for additive Gaussian noise.
      observation_noise_cov: optional ``R[m, m]`` for additive Gaussian noise, or ``R[m]``, its
        diagonal (independent noise per component: the built-in models; the square-root EnKF and
        the LETKF then never form an m x m matrix, which is what lets Lorenz-96 run at
        m = 40,000; the perturbed EnKF's gain is m x m whatever R).
      parameters: optional pytree of arrays a built-in model keeps (e.g. the matrices of a
        linear-Gaussian model for the exact Kalman filter).
      observation_noise_factors: optional ``(L, L^{-1})``, the Cholesky factor of R and its
        inverse (for a diagonal ``R[m]``, the vectors of standard deviations and their inverses). Leave it None: ``run_filter`` fills it once before its scan (see
        ``with_observation_noise_factors``) so that the EnKF does not refactor the constant R at
        every step; updates called directly factor R themselves.
    """

    sample_initial: Callable[[Array], Array]
    sample_transition: Callable[[Array, Array], Array]
    sample_observation: Callable[[Array, Array], Array]
    log_likelihood: Callable[[Array, Array], Array] | None = None
    observation_function: Callable[[Array], Array] | None = None
    observation_noise_cov: Array | None = None
    parameters: Any = None
    observation_noise_factors: tuple[Array, Array] | None = None
    geometry: Any = None  # optional localisation.Geometry: where state and observations lie


    @property
    def has_gaussian_observation_noise(self) -> bool:
        """True when ``h`` and ``R`` are both given (additive Gaussian observation noise)."""
        return self.observation_function is not None and self.observation_noise_cov is not None


_FUNCTION_FIELDS = (
    "sample_initial",
    "sample_transition",
    "sample_observation",
    "log_likelihood",
    "observation_function",
)


def _flatten(model: StateSpaceModel):
    functions = tuple(getattr(model, name) for name in _FUNCTION_FIELDS)
    # A function bound with lib.static.bind (a jax Partial) is a subtree: its numbers are leaves
    # and its static part compares by value. Any other function is static aux, by identity.
    is_tree = tuple(isinstance(function, jax.tree_util.Partial) for function in functions)
    trees = tuple(function if tree else None for function, tree in zip(functions, is_tree))
    static = tuple(None if tree else function for function, tree in zip(functions, is_tree))
    children = (trees, model.observation_noise_cov, model.parameters, model.observation_noise_factors,
                model.geometry)
    return children, (static, is_tree)


def _unflatten(aux, children) -> StateSpaceModel:
    static, is_tree = aux
    trees, *arrays = children
    functions = (tree if flag else function for tree, function, flag in zip(trees, static, is_tree))
    return StateSpaceModel(*functions, *arrays)


# Functions are static aux data (hashable by identity) unless bound with lib.static.bind (then
# subtrees); arrays are traced leaves.
jax.tree_util.register_pytree_node(StateSpaceModel, _flatten, _unflatten)


def with_observation_noise_factors(model: StateSpaceModel, dtype=None) -> StateSpaceModel:
    """``model`` with ``observation_noise_factors = (L, L^{-1})`` of its R (unchanged without R),
    computed in R's dtype promoted with ``dtype`` (the particles'): a float32 R in a float64
    filter is factored in float64, as the EnKF did before the factors were cached.

    Called by ``run_filter`` outside its scan. The factors must stay those of the model's R, so
    this is done per run, never stored on a model that a user may ``_replace`` R in (a model
    returned by this function and then given a new R would keep the old factors): inside a
    ``lax.cond`` branch (the update of a step that has an observation) XLA cannot hoist R's
    loop-invariant factorisation out of the loop, and on Lorenz-96 (m = 40) refactoring R at
    every step was a third of a square-root EnKF cycle.
    """
    if model.observation_noise_cov is None:
        return model
    noise_cov = jnp.asarray(model.observation_noise_cov)
    if dtype is not None:
        noise_cov = noise_cov.astype(jnp.promote_types(noise_cov.dtype, dtype))
    if noise_cov.ndim == 1:  # diagonal R: standard deviations and their inverses
        std = jnp.sqrt(noise_cov)
        return model._replace(observation_noise_factors=(std, 1.0 / std))
    chol = jnp.linalg.cholesky(noise_cov)
    inverse = jax.scipy.linalg.solve_triangular(
        chol, jnp.eye(noise_cov.shape[0], dtype=chol.dtype), lower=True
    )
    return model._replace(observation_noise_factors=(chol, inverse))


def observation_noise_factors(model: StateSpaceModel, dtype) -> tuple[Array, Array]:
    """``(L, L^{-1})`` of the model's R in ``dtype``: the stored ones, else computed here."""
    if model.observation_noise_factors is None:
        model = with_observation_noise_factors(model, dtype)
    chol, inverse = model.observation_noise_factors
    return jnp.asarray(chol, dtype), jnp.asarray(inverse, dtype)


def observed_noise_factors(model: StateSpaceModel, observed: Array, dtype) -> tuple[Array, Array]:
    """The factors of R restricted to the ``observed[m]`` components, for ``whiten``: with a
    diagonal R, R's own (the caller zeroes the missing components); with a full R, those of
    R~ = R on the observed block and the identity elsewhere, whose Cholesky factor has the same
    block structure (no fill-in), so that whitening the observed components is exactly by
    L_oo^{-1}. The constant factors are reused when everything is observed (a ``cond``)."""
    factors = observation_noise_factors(model, dtype)
    if factors[0].ndim == 1:
        return factors

    def masked():
        noise_cov = jnp.asarray(model.observation_noise_cov, dtype)
        identity = jnp.eye(noise_cov.shape[0], dtype=dtype)
        chol = jnp.linalg.cholesky(jnp.where(observed[:, None] & observed[None, :], noise_cov, identity))
        return chol, jax.scipy.linalg.solve_triangular(chol, identity, lower=True)

    return jax.lax.cond(jnp.all(observed), lambda: factors, masked)


def colour_noise(factors: tuple[Array, Array], standard: Array) -> Array:
    """``standard[..., m] @ L^T``: standard normals to N(0, R) noise (``factors = (L, L^{-1})``)."""
    chol, _ = factors
    return standard * chol if chol.ndim == 1 else standard @ chol.T


def observation_noise(key: Array, model: StateSpaceModel, num: int, m: int, dtype) -> Array:
    """``[num, m]`` draws of N(0, R), the model's observation noise. Component k's ``num``
    standard normals come from its own key (fold_in k): they do not depend on m, so deleting
    trailing components leaves the others' draws (and L's leading block is the Cholesky factor of
    R's leading block), and each stream is prefix-consistent in ``num`` (a padded particle axis,
    ``updates.base``)."""
    return colour_noise(observation_noise_factors(model, dtype), _standard_normals(key, num, m, dtype).T)


def _standard_normals(key: Array, num: int, m: int, dtype) -> Array:
    """``[m, num]``: component k's ``num`` standard normals from key fold_in(key, k)."""
    return jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(key, k), (num,), dtype))(jnp.arange(m))


def simulate_observations(key: Array, model: StateSpaceModel, particles: Array) -> Array:
    """``[N, m]``: Y^i ~ h(. | X^i) for each row of ``particles[N, n]``. With additive Gaussian
    noise (``h`` and ``R`` given), h(X^i) plus ``observation_noise``'s draws, else
    ``sample_observation`` with a key per particle. Why: XLA's CPU draws a few normals for each of
    N keys several times slower than N for each of m keys (at n = m = 10, N = 1000, the dynamic
    example's observations cost the localised OT update as much as the EnKF's whole step)."""
    if not model.has_gaussian_observation_noise:
        return jax.vmap(model.sample_observation)(jax.random.split(key, particles.shape[0]), particles)
    predicted = jax.vmap(model.observation_function)(particles)
    factors = observation_noise_factors(model, predicted.dtype)
    standard = _standard_normals(key, predicted.shape[0], predicted.shape[1], predicted.dtype)
    if factors[0].ndim == 1:
        # The sum formed [m, N] and transposed once: drawn into an [N, m] sum, the normals were
        # computed in a transposing loop that XLA's CPU does not vectorise (2.4 times as slow).
        return (predicted.T + factors[0][:, None] * standard).T
    return predicted + colour_noise(factors, standard.T)


def whiten(factors: tuple[Array, Array], values: Array) -> Array:
    """``L^{-1} v`` for each row ``v`` of ``values[..., m]`` (``factors = (L, L^{-1})``)."""
    _, inverse = factors
    return values * inverse if inverse.ndim == 1 else values @ inverse.T


def dense_noise_cov(noise_cov: Array) -> Array:
    """R as an ``[m, m]`` matrix (a diagonal ``R[m]`` expanded)."""
    noise_cov = jnp.asarray(noise_cov)
    return jnp.diag(noise_cov) if noise_cov.ndim == 1 else noise_cov


def model_dimensions(model: StateSpaceModel) -> tuple[int, int]:
    """Returns ``(n, m)``, the state and observation dimensions, by abstract evaluation."""
    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    key = jax.random.key(0)
    try:
        x = jax.eval_shape(model.sample_initial, key)
    except Exception as error:  # noqa: BLE001 - re-raised with the argument named
        raise TypeError(f"model.sample_initial(key) failed: {error}") from error
    if x.ndim != 1:
        raise ValueError(f"model.sample_initial must return a state x[n], got shape {x.shape}")
    x_next = jax.eval_shape(model.sample_transition, key, x)
    if x_next.shape != x.shape:
        raise ValueError(
            f"model.sample_transition must return shape {x.shape} (state x[n]), got {x_next.shape}"
        )
    y = jax.eval_shape(model.sample_observation, key, x)
    if y.ndim != 1:
        raise ValueError(
            f"model.sample_observation must return an observation y[m], got shape {y.shape}"
        )
    n, m = x.shape[0], y.shape[0]
    if model.observation_function is not None:
        hx = jax.eval_shape(model.observation_function, x)
        if hx.shape != (m,):
            raise ValueError(
                f"model.observation_function must return shape ({m},) like sample_observation, "
                f"got {hx.shape}"
            )
    if model.observation_noise_cov is not None:
        check_covariance("model.observation_noise_cov", model.observation_noise_cov, m, True,
                         allow_diagonal=True)
    geometry = model.geometry
    if geometry is not None:
        sizes = (jnp.shape(getattr(geometry, "state_positions", ()))[:1],
                 jnp.shape(getattr(geometry, "observation_positions", ()))[:1])
        if sizes != ((n,), (m,)):
            raise ValueError(
                f"model.geometry must place the {n} state coordinates and {m} observation "
                f"components (a localisation.Geometry), got {sizes[0]} and {sizes[1]} positions"
            )
    if model.log_likelihood is not None:
        value = jax.eval_shape(model.log_likelihood, y, x)
        if value.shape != ():
            raise ValueError(
                f"model.log_likelihood(y, x) must return a scalar, got shape {value.shape}"
            )
    return n, m


def simulate(key: Array, model: StateSpaceModel, num_steps: int) -> tuple[Array, Array]:
    """Draws a trajectory of the model.

    ``X_0 ~ pi_0``; for ``t = 1..T``: ``X_t ~ a(. | X_{t-1})``, ``Y_t ~ h(. | X_t)``.

    Args:
      key: PRNG key.
      model: the state-space model.
      num_steps: T, the number of observation times (static).

    Returns:
      ``(states[T, n], observations[T, m])``: the hidden states X_1..X_T and observations
      Y_1..Y_T (X_0 is not returned; filters start from pi_0, like the truth).
    """
    if not isinstance(num_steps, int) or num_steps < 1:
        raise ValueError(f"num_steps must be a positive int, got {num_steps!r}")
    model_dimensions(model)
    return _simulate(key, model, num_steps)


@partial(jax.jit, static_argnums=2)
def _simulate(key, model, num_steps):
    init_key, steps_key = jax.random.split(key)
    x0 = model.sample_initial(init_key)

    def step(x, step_key):
        transition_key, observation_key = jax.random.split(step_key)
        x = model.sample_transition(transition_key, x)
        y = model.sample_observation(observation_key, x)
        return x, (x, y)

    _, (states, observations) = jax.lax.scan(step, x0, jax.random.split(steps_key, num_steps))
    return states, observations
