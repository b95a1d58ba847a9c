"""``HomesPredictor``: a trained homes model as a prior over receptacles, and its samples.

    predictor = HomesPredictor.load("runs/homes/checkpoints")   # best step; or "flowmaps-homes"
    p = predictor.probabilities(homes, queries, config)          # (E, Q, R), rows sum to 1
    boxes = predictor.sample(jax.random.key(0), homes, queries, config, num_samples=16)

``probabilities`` are the model's mixture weights over each object's allowed receptacles, read
without sampling: a prior ``(homes, queries) -> (E, Q, R)`` as :mod:`flowmaps_jax.homes.queries`
defines it (:meth:`HomesPredictor.as_prior`). ``sample`` draws a receptacle from the weights and a
6-D box (cx, cy, cz, w, d, h) in metres from the placement flow on it. Each query is one scene:
home e at its own τ (the object tokens of that hour) with the object's history up to τ.

Inputs are checked here (``ValueError`` naming the argument); the jitted cores are
:mod:`flowmaps_jax.homes.model`'s. Loading reads checkpoints and packaged weights through
:mod:`flowmaps_jax.store` (checksums, member whitelist, finiteness), like the 2-D models.
"""

from __future__ import annotations

import functools
import pathlib

import jax
import jax.numpy as jnp

from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.homes.world import Homes, validate_homes
from flowmaps_jax.homes.model import (
    DEFAULT_NUM_STEPS,
    FAMILY_NAME,
    HomesModelConfig,
    receptacle_probabilities,
    sample_placements,
)
from flowmaps_jax.homes.queries import HomesQueries, check_queries
from flowmaps_jax.homes.tokens import denormalise_boxes, per_query_batch
from flowmaps_jax.store import checkpoints, pretrained
from flowmaps_jax.validation import (
    check_choice,
    check_instance,
    check_int,
    check_key,
    check_request_size,
    prefix_errors,
)

PRETRAINED_PREFIX = pretrained.PREFIX
COMPATIBLE_FIELDS = ("rooms", "receptacles_per_room", "objects_per_home", "max_tokens",
                     "max_vocabulary", "room_types", "receptacle_classes", "object_classes")
"""The config fields a model's token layout and vocabulary depend on: a config given to the
predictor must agree with the model's on these (the schedules may differ)."""

ROWS_PER_CALL = 8192
"""Query rows one compiled call takes at most (queries × samples); larger requests run in
chunks of queries of one padded shape (one compiled program), so memory stays bounded."""

_query_batch = jax.jit(per_query_batch, static_argnames=("config", "history"))


def _window(a, start: int, size: int):
    """Columns start … start + size − 1 of a (E, Q, …), padded with copies of column 0."""
    part = a[:, start:start + size]
    return jnp.concatenate([part, jnp.repeat(a[:, :1], size - part.shape[1], 1)], 1)


def _head(a, count: int):
    return a[:, :count]


class HomesPredictor:
    """A trained homes model: ``params``, its ``model`` sizes, the ``homes`` config it was
    trained on, where it came from (``source``) and its training ``step``."""

    def __init__(self, params, model: HomesModelConfig, homes: HomesConfig,
                 source: str = "params", step: int | None = None):
        check_instance("params", params, dict)
        check_instance("model", model, HomesModelConfig)
        check_instance("homes", homes, HomesConfig)
        with prefix_errors("homes."):
            homes.validate()  # the token budget too, should a config have skipped its checks
        self.params, self.model, self.homes = params, model, homes
        self.source, self.step = source, step

    # ------------------------------------------------------------------ loading

    @classmethod
    def load(cls, source, which: str = "best",
             directory: str | pathlib.Path = pretrained.PRETRAINED_DIR) -> HomesPredictor:
        """The model in ``source``: a run or checkpoint directory (its ``which`` step: "best",
        the lowest validation CE, by default; "latest" its last), or a packaged name such as
        ``"flowmaps-homes"`` (also as ``"pretrained:flowmaps-homes"``), read from
        ``directory`` (the package's weights by default). ``ValueError`` naming ``source`` when
        it is missing, damaged or not a homes model."""
        which = check_choice("which", which, checkpoints.WHICH)
        check_instance("source", source, (str, pathlib.Path))
        text = str(source)
        name = text[len(PRETRAINED_PREFIX):] if text.startswith(PRETRAINED_PREFIX) else text
        packaged = text.startswith(PRETRAINED_PREFIX) or (
            name in pretrained.NAMES and not pathlib.Path(name).exists())
        with prefix_errors(f"source {text!r}: "):
            if packaged:
                weights = pretrained.read_weights(name, directory)
                where, step = f"pretrained:{name}", weights.step
            else:
                weights = checkpoints.load_weights(source, which)
                where, step = str(weights.root), weights.step
        if weights.spec.family_name != FAMILY_NAME:
            raise ValueError(f"source {text!r} holds a {weights.spec.family_name!r} model, not a "
                             f"{FAMILY_NAME!r} one")
        return cls(weights.params, weights.spec.model, weights.spec.homes, where, step)

    # ------------------------------------------------------------------ inference

    def check(self, homes: Homes, queries: HomesQueries, config: HomesConfig) -> None:
        """``ValueError`` naming the argument unless ``config`` agrees with the model's on the
        token layout and vocabulary (:data:`COMPATIBLE_FIELDS`) and ``homes`` / ``queries`` fit
        ``config``."""
        validate_homes(homes, config, values=False)  # config is a HomesConfig from here on
        for field in COMPATIBLE_FIELDS:
            if getattr(config, field) != getattr(self.homes, field):
                raise ValueError(f"config.{field} differs from the model's (trained on "
                                 f"{field}={str(getattr(self.homes, field))[:80]}): the tokens "
                                 f"would mean something else")
        check_queries(queries, homes, config)

    def _batch(self, homes, queries):
        return _query_batch(homes, queries, self.homes, self.model.history)

    def _chunked(self, fn, queries: HomesQueries, rows_per_query: int):
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

    def probabilities(self, homes: Homes, queries: HomesQueries,
                      config: HomesConfig) -> jax.Array:
        """(E, Q, R) float32: the model's probability that each queried object stands on
        receptacle slot r at τ_q; 0 off its allowed receptacles, rows sum to 1."""
        self.check(homes, queries, config)
        e = queries.tau.shape[0]

        def run(chunk):
            p = receptacle_probabilities(self.params, self.model, self.homes,
                                         self._batch(homes, chunk))
            return p.reshape(e, chunk.tau.shape[1], -1)

        return self._chunked(run, queries, self.homes.max_receptacles)

    def sample(self, key, homes: Homes, queries: HomesQueries, config: HomesConfig,
               num_samples: int, num_steps: int = DEFAULT_NUM_STEPS, *,
               return_receptacles: bool = False):
        """(E, Q, N, 6) float32 boxes (cx, cy, cz, w, d, h) in metres: a receptacle drawn from
        the weights, then the placement flow on it (``num_steps`` midpoint grid points). With
        ``return_receptacles``: (boxes, receptacles (E, Q, N) int32)."""
        key = check_key(key)
        num_samples = check_int("num_samples", num_samples)
        num_steps = check_int("num_steps", num_steps, 2)
        self.check(homes, queries, config)
        e, q = queries.tau.shape
        check_request_size(f"sample({e} x {q} queries x {num_samples} samples)",
                           e * q * num_samples * 6 * 4 * 2)  # the boxes and receptacles
        calls = iter(range(q))  # chunk k draws with fold_in(key, k)

        def run(chunk):
            qc = chunk.tau.shape[1]
            table, boxes = sample_placements(self.params, self.model, self.homes,
                                             self._batch(homes, chunk),
                                             jax.random.fold_in(key, next(calls)), num_samples,
                                             num_steps)
            return table.reshape(e, qc, num_samples), boxes.reshape(e, qc, num_samples, 6)

        table, boxes = self._chunked(run, queries, num_samples + self.homes.max_receptacles)
        boxes = denormalise_boxes(boxes, homes.home_size)
        return (boxes, table) if return_receptacles else boxes

    def as_prior(self, config: HomesConfig):
        """``prior(homes, queries) -> (E, Q, R)``: :meth:`probabilities` for ``config``."""
        return functools.partial(self._prior, config=config)

    def _prior(self, homes, queries, config):
        return self.probabilities(homes, queries, config)

    def __repr__(self) -> str:
        return (f"HomesPredictor(source={self.source!r}, step={self.step}, "
                f"dim={self.model.dim})")
