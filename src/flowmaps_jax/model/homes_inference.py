"""The one :class:`flowmaps_jax.predictor.Predictor` on a FlowSim homes model: its inference.

    predictor = load_model("runs/homes")        # or load_pretrained("flowmaps-homes")
    p = predictor.probabilities(homes, queries, config)          # (E, Q, R), rows sum to 1
    boxes = predictor.sample(homes, queries, 16, jax.random.key(0), config=config)
    p = predictor.probabilities(homes, queries, config, observed=observed)  # partial logs

``observed`` (E, T, M) bool says which hours each object was seen (``homes.receptacle`` holds
where it was last seen); None: every hour. A model trained on partially observed data
(``history_observed``) refuses a query without it. ``not_at`` (E, T, M, R) bool: object m was
looked for on receptacle r at hour t and was not there (read by a model with
``negative_evidence``; None: no such looks).

The :class:`~flowmaps_jax.predictor.Predictor` of a homes model (its family's world is
``"homes"``) calls these functions (that world's ``Inference``, not a branch):
``probabilities`` are the model's mixture weights over each object's allowed receptacles, read
without sampling, a prior ``(homes, queries) -> (E, Q, R)`` as
:mod:`flowmaps_jax.flowsim.homes.queries` defines it (:func:`as_prior`); ``sample`` draws a
receptacle from the weights and a 6-D box (cx, cy, cz, w, d, h) in metres from the placement
flow on it. Each query is one scene: home e
at its own τ (the object tokens of that hour) with the object's history up to τ.

Inputs are checked here (``ValueError`` naming the argument); the jitted cores are
:mod:`flowmaps_jax.model.homes_family`'s.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.homes.queries import HomesQueries, check_queries
from flowmaps_jax.flowsim.homes.world import Homes, validate_homes
from flowmaps_jax.model.homes_family import (
    DEFAULT_NUM_STEPS,
    HomesModelConfig,
    receptacle_probabilities,
    sample_placements,
)
from flowmaps_jax.model.homes_inputs import (
    HomeTokens,
    denormalise_boxes,
    per_query_batch,
    scene_tokens,
)
from flowmaps_jax.resources import check_resources, solver_evaluations
from flowmaps_jax.validation import (
    check_concrete,
    check_flag,
    check_instance,
    check_int,
    check_int_array,
    check_key,
    check_mask,
    prefix_errors,
)

COMPATIBLE_FIELDS = ("rooms", "receptacles_per_room", "objects_per_home", "max_tokens",
                     "max_vocabulary", "room_types", "receptacle_classes", "object_classes")
"""The config fields a model's token layout and vocabulary depend on: a config given to the
predictor must agree with the model's on these (the schedules may differ)."""

ROWS_PER_CALL = 8192
"""Query rows one compiled call takes at most (queries × samples); larger requests run in
chunks of queries of one padded shape (one compiled program), so memory stays bounded."""

_query_batch = jax.jit(per_query_batch, static_argnames=("config", "history", "negative"))


def _window(a, start: int, size: int):
    """Columns start … start + size − 1 of a (E, Q, …), padded with copies of column 0."""
    part = a[:, start:start + size]
    return jnp.concatenate([part, jnp.repeat(a[:, :1], size - part.shape[1], 1)], 1)


def _head(a, count: int):
    return a[:, :count]


def check_model(predictor) -> None:
    """A homes predictor's fields: ``params`` a dict, ``model`` a
    :class:`~flowmaps_jax.model.homes_family.HomesModelConfig`, ``homes`` a valid
    :class:`~flowmaps_jax.flowsim.homes.HomesConfig` (ValueError naming the field)."""
    check_instance("params", predictor.params, dict)
    check_instance("model", predictor.model, HomesModelConfig)
    check_instance("homes", predictor.homes, HomesConfig)
    with prefix_errors("homes."):
        predictor.homes.validate()  # the token budget too, should a config skip its checks


_scene_tokens = jax.jit(scene_tokens, static_argnums=2)  # one program, not one per operation


def home_tokens(homes: Homes, tau, config: HomesConfig) -> HomeTokens:
    """Tokens of every home at hour ``tau``: (E,) ints → (E, S); (E, K) → (E, K, S)."""
    check_instance("config", config, HomesConfig)
    tau = check_int_array("tau", tau, 0, config.num_hours - 1)
    with prefix_errors("config."):
        config.validate()
    validate_homes(homes, config, values=False)
    e = homes.num_homes
    if tau.ndim not in (1, 2) or tau.shape[0] != e:
        raise ValueError(f"tau must have shape (E={e},) or (E, K); got {tau.shape}")
    out = _scene_tokens(homes, tau.astype(jnp.int32).reshape(e, -1), config)
    return jax.tree.map(lambda a: a[:, 0], out) if tau.ndim == 1 else out


def check(predictor, homes: Homes, queries: HomesQueries, config: HomesConfig,
          what: str = "the query", observed=None, not_at=None):
    """``ValueError`` naming the argument unless ``config`` agrees with the model's on the
    token layout and vocabulary (:data:`COMPATIBLE_FIELDS`) and ``homes`` / ``queries`` fit
    ``config``: finite, sensible home arrays (``validate_homes`` with values), at least one
    home and one query per home, concrete arrays (``what`` is not run under ``jax.jit``).
    Returns (observed, not_at) as arrays (or None)."""
    check_concrete(f"{what} of a homes model", homes, queries)
    validate_homes(homes, config)  # config is a HomesConfig from here on; values too
    if homes.num_homes == 0:
        raise ValueError("homes must hold at least one home; got 0")
    for field in COMPATIBLE_FIELDS:
        if getattr(config, field) != getattr(predictor.homes, field):
            raise ValueError(f"config.{field} differs from the model's (trained on "
                             f"{field}={str(getattr(predictor.homes, field))[:80]}): the tokens "
                             f"would mean something else")
    check_queries(queries, homes, config)
    if queries.tau.shape[1] == 0:
        raise ValueError("queries must hold at least one query per home; got shape "
                         f"{tuple(queries.tau.shape)}")
    if not_at is not None:
        not_at = jnp.asarray(check_mask("not_at", not_at, (*homes.receptacle.shape,
                                                           homes.receptacle_class.shape[-1])))
    if observed is None:
        if predictor.model.history_observed:
            raise ValueError("observed is required: this model was trained on partially "
                             "observed data; pass observed (E, T, M) bool, the hours each "
                             "object was seen (all True if every hour was)")
        return None, not_at
    return jnp.asarray(check_mask("observed", observed, tuple(homes.receptacle.shape))), not_at


def _chunked(fn, queries: HomesQueries, rows_per_query: int):
    """``fn(queries chunk)`` over chunks of the query axis (the last padded with copies of
    the first query), concatenated along it: one compiled shape however many queries."""
    queries = jax.tree.map(lambda a: jnp.asarray(a, jnp.int32), queries)
    e, q = queries.tau.shape
    size = max(1, min(q, ROWS_PER_CALL // max(e * rows_per_query, 1)))
    if size == q:
        return fn(queries)
    parts = [jax.tree.map(functools.partial(_head, count=min(size, q - start)),
                          fn(jax.tree.map(functools.partial(_window, start=start,
                                                            size=size), queries)))
             for start in range(0, q, size)]
    return jax.tree.map(lambda *a: jnp.concatenate(a, axis=1), *parts)


def probabilities(predictor, homes: Homes, queries: HomesQueries,
                  config: HomesConfig | None = None, observed=None, not_at=None) -> jax.Array:
    """(E, Q, R) float32: the model's probability that each queried object stands on
    receptacle slot r at τ_q; 0 off its allowed receptacles, rows sum to 1. ``config``: the
    config the homes were generated with (default: the model's); ``observed``, ``not_at``: see
    above."""
    config = predictor.homes if config is None else config
    observed, not_at = check(predictor, homes, queries, config, "probabilities", observed,
                             not_at)
    e = queries.tau.shape[0]

    def run(chunk):
        p = receptacle_probabilities(predictor.params, predictor.model, predictor.homes,
                                     _query_batch(homes, chunk, predictor.homes,
                                                  predictor.model.history, observed, not_at,
                                                  predictor.model.negative_evidence))
        return p.reshape(e, chunk.tau.shape[1], -1)

    return _chunked(run, queries, predictor.homes.max_receptacles)


def sample(predictor, homes: Homes, queries: HomesQueries, num_samples: int, key,
           num_steps: int = DEFAULT_NUM_STEPS, *, config: HomesConfig | None = None,
           observed=None, return_receptacles: bool = False, not_at=None):
    """(E, Q, N, 6) float32 boxes (cx, cy, cz, w, d, h) in metres: a receptacle drawn from
    the weights, then the placement flow on it (``num_steps`` midpoint grid points). With
    ``return_receptacles``: (boxes, receptacles (E, Q, N) int32)."""
    check_concrete("sample of a homes model", key)
    key = check_key(key)
    num_samples = check_int("num_samples", num_samples)
    num_steps = check_int("num_steps", num_steps, 2)
    return_receptacles = check_flag("return_receptacles", return_receptacles)
    config = predictor.homes if config is None else config
    observed, not_at = check(predictor, homes, queries, config, "sample", observed, not_at)
    e, q = queries.tau.shape
    check_resources(  # the shared budget: the boxes and receptacles, the solve's evaluations
        f"sample({e} x {q} queries x {num_samples} samples, num_steps={num_steps})",
        num_bytes=e * q * num_samples * 6 * 4 * 2, sequential=solver_evaluations(num_steps))
    calls = iter(range(q))  # chunk k draws with fold_in(key, k)

    def run(chunk):
        qc = chunk.tau.shape[1]
        table, boxes = sample_placements(predictor.params, predictor.model, predictor.homes,
                                         _query_batch(homes, chunk, predictor.homes,
                                                      predictor.model.history, observed,
                                                      not_at, predictor.model.negative_evidence),
                                         jax.random.fold_in(key, next(calls)), num_samples,
                                         num_steps)
        return table.reshape(e, qc, num_samples), boxes.reshape(e, qc, num_samples, 6)

    table, boxes = _chunked(run, queries, num_samples + predictor.homes.max_receptacles)
    boxes = denormalise_boxes(boxes, homes.home_size)
    return (boxes, table) if return_receptacles else boxes


def as_prior(predictor, config: HomesConfig | None = None, observed=None, not_at=None):
    """``prior(homes, queries) -> (E, Q, R)``: :func:`probabilities` for ``config``."""
    return functools.partial(_prior, predictor, config=config, observed=observed, not_at=not_at)


def _prior(predictor, homes, queries, config, observed, not_at):
    return probabilities(predictor, homes, queries, config, observed, not_at)
