"""Reference rows with an exact answer, for recorded data made from FlowSim homes
(docs/protocol.md, "Exact reference rows").

An environment written by ``python -m flowmaps_jax.data from-homes`` keeps the config, the home
e, the seed S and the count N in its ``source``, so home e of ``generate_homes(key(S), config,
N)`` is regenerated (``homes_from_keys``), hidden law included. :func:`reference_rows` gives
``EXACT_ROW`` (``homes_history_posterior`` given the true receptacles of the last week, the
favourites hidden) and ``FILTER_ROW`` (``filtered_posterior`` over the observed hours only),
both mapped to the recorded order (receptacle j is slot ``slots[j]``, object m slot
``objects[m]``). Other data gets no such rows, and a one-line note says why.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.homes.config import REGIMES, HomesConfig
from flowmaps_jax.flowsim.homes.posterior import filtered_posterior, homes_history_posterior
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.flowsim.homes.rollout import homes_from_keys

EXACT_HISTORY = 168
"""Hours of true history the exact row reads (a week, as the homes evaluation's exact row)."""
EXACT_ROW = f"exact posterior (H = {EXACT_HISTORY} h)"
FILTER_ROW = "known-parameters filter (ceiling)"
QUERIES_PER_CALL = 1024
"""Queries per compiled call (environments per call: this ÷ Q; the last call padded)."""


@dataclasses.dataclass(frozen=True)
class HomesSource:
    """Where every environment of a dataset came from: home ``homes[i]`` (E,) of
    ``generate_homes(jax.random.key(seed), config, num_homes)``."""

    config: HomesConfig
    seed: int
    num_homes: int
    homes: np.ndarray


def homes_source(environments) -> HomesSource | str:
    """The FlowSim homes the ``environments`` (a sequence of ``recorded.Environment``) were
    written from by ``from-homes``, or a one-line reason why they cannot be regenerated."""
    if not environments:
        return "no environment"
    first, homes = None, []
    for env in environments:
        src = env.source if isinstance(env.source, dict) else {}
        where = f"environment {env.name!r}"
        if src.get("from") != "flowsim-homes":
            return f"{where} is not FlowSim homes (its source says from={src.get('from')!r})"
        gen = src.get("generator")
        if not isinstance(gen, dict) or not all(isinstance(gen.get(k), int) and not
                                                isinstance(gen.get(k), bool)
                                                for k in ("seed", "num_homes")):
            return f"{where}: its source has no generator seed (not written by from-homes)"
        home = src.get("home")
        if not isinstance(home, int) or not 0 <= home < gen["num_homes"]:
            return f"{where}: its source's home {home!r} is not one of {gen['num_homes']}"
        key = (json.dumps(src.get("config"), sort_keys=True), gen["seed"], gen["num_homes"])
        if first is None:
            first = key
        elif key != first:
            return f"{where} comes from another from-homes call than the first environment"
        homes.append(home)
    try:
        config = HomesConfig.from_dict(json.loads(first[0]))
    except (ValueError, TypeError) as err:
        return f"the source's homes config is not readable ({' '.join(str(err).split())})"[:300]
    return HomesSource(config=config, seed=first[1], num_homes=first[2],
                       homes=np.asarray(homes, np.int64))


def _numbering(env, home: dict, config: HomesConfig) -> tuple[np.ndarray, np.ndarray] | str:
    """(slots (R_e,), objects (M_e,)): the regenerated ``home``'s (numpy fields of one home)
    valid receptacle and object slots, in the recorded order; a reason when the environment is
    not that home (its receptacles, objects, allowed places or sightings differ)."""
    slots = np.flatnonzero(home["receptacle_valid"])
    objects = np.flatnonzero(home["object_valid"])
    where = f"environment {env.name!r} is not its regenerated home"
    names = tuple(f"{config.receptacle_classes[c].name}|{s}"
                  for c, s in zip(home["receptacle_class"][slots], slots, strict=True))
    if (names != tuple(env.receptacle_ids) or len(objects) != env.num_objects
            or not np.array_equal(home["object_allowed"][np.ix_(objects, slots)], env.allowed)):
        return f"{where} (its receptacles, objects or allowed places differ)"
    hours = np.asarray(env.hours)
    if hours.size and (hours[0] < 0 or hours[-1] >= config.num_hours):
        return f"{where} (hours beyond the home's {config.num_hours})"
    location = np.asarray(env.location)
    seen = location >= 0
    truth = home["receptacle"][hours][:, objects]  # (T_e, M_e) slots
    if not np.array_equal(slots[location[seen]], truth[seen]):
        return f"{where} (an object is seen where the home's object is not)"
    return slots, objects


@functools.partial(jax.jit, static_argnames=("config", "history"))
def _rows(homes, observed, queries: HomesQueries, config: HomesConfig, history: int):
    """((E, Q, R), (E, Q, R)): the exact and filtered rows in the homes' own slots."""
    def one(home, seen, i, tau, tau_q):
        exact = homes_history_posterior(home, i, tau, tau_q, jnp.minimum(history, tau + 1),
                                        config)
        return exact, filtered_posterior(home, i, seen, tau, tau_q, config)

    per_query = jax.vmap(one, in_axes=(None, None, 0, 0, 0))
    return jax.vmap(per_query)(homes, observed, queries.object_index, queries.tau,
                               queries.tau_q)


def reference_rows(environments, data, queries: HomesQueries,
                   history: int = EXACT_HISTORY
                   ) -> tuple[dict[str, np.ndarray], str, np.ndarray | None]:
    """({``EXACT_ROW``: (E, Q, R), ``FILTER_ROW``: (E, Q, R)}, a one-line note, the regime
    name of each query's object (E, Q)) for the E environments of ``data`` (a
    ``worlds.recorded.RecordedHomes``; ``environments`` the recorded ones it was built from, in
    its order) and its ``queries`` (E, Q), in ``data``'s receptacle slots; ({}, the reason,
    None) when they are not all FlowSim homes that ``from-homes`` wrote (see the module
    docstring)."""
    source = homes_source(environments)
    if isinstance(source, str):
        return {}, f"No exact reference rows: {source}.", None
    config = source.config
    e, q = np.asarray(queries.tau).shape
    r_data, m_data = (data.homes.receptacle_valid.shape[-1], data.homes.object_valid.shape[-1])
    t = config.num_hours
    history = min(history, t)
    observed = np.asarray(data.observed)
    if observed.shape[1] < t:
        return {}, (f"No exact reference rows: the data's homes hold {observed.shape[1]} hours, "
                    f"the FlowSim homes {t}."), None
    obj, tau, tau_q = (np.asarray(a) for a in (queries.object_index, queries.tau,
                                               queries.tau_q))
    keys = jax.random.split(jax.random.key(source.seed), source.num_homes)
    chunk = max(1, min(e, QUERIES_PER_CALL // max(q, 1)))
    rows = {EXACT_ROW: np.zeros((e, q, r_data), np.float32),
            FILTER_ROW: np.zeros((e, q, r_data), np.float32)}
    regime = np.zeros((e, q), np.int64)
    for start in range(0, e, chunk):
        index = np.arange(start, start + chunk)
        real = index < e
        index = np.where(real, index, start)  # the last chunk padded: one compiled shape
        homes = homes_from_keys(keys[source.homes[index]], config)
        fields = {k: np.asarray(v) for k, v in homes.as_dict().items()}
        to_slot = np.zeros((chunk, r_data), np.int64)  # data slot j -> home slot (or -1)
        to_object = np.zeros((chunk, m_data), np.int64)
        seen = np.zeros((chunk, t, config.max_objects), bool)
        for c in np.flatnonzero(real):
            env = environments[index[c]]
            numbering = _numbering(env, {k: v[c] for k, v in fields.items()}, config)
            if isinstance(numbering, str):
                return {}, f"No exact reference rows: {numbering}.", None
            slots, objects = numbering
            to_slot[c] = -1
            to_slot[c, :len(slots)] = slots
            to_object[c] = objects[0]  # padding objects: any valid one (never a valid query)
            to_object[c, :len(objects)] = objects
            seen[c][:, objects] = observed[index[c], :t, :len(objects)]
        home_queries = HomesQueries(
            object_index=jnp.asarray(np.take_along_axis(to_object, obj[index], 1), jnp.int32),
            tau=jnp.asarray(np.minimum(tau[index], t - 2), jnp.int32),
            tau_q=jnp.asarray(np.clip(tau_q[index], np.minimum(tau[index], t - 2) + 1, t - 1),
                              jnp.int32))
        exact, ceiling = _rows(homes, jnp.asarray(seen), home_queries, config, history)
        for name, p in ((EXACT_ROW, exact), (FILTER_ROW, ceiling)):
            p = np.take_along_axis(np.asarray(p), np.maximum(to_slot, 0)[:, None, :], 2)
            p = np.where(to_slot[:, None, :] >= 0, np.nan_to_num(p), 0.0)
            rows[name][index[real]] = p[real]
        regime[index[real]] = np.take_along_axis(
            fields["regime"], np.asarray(home_queries.object_index), 1)[real]
    note = (f"Exact reference rows (the environments are FlowSim homes {config.regime!r}, "
            f"regenerated from their source: seed {source.seed}, {source.num_homes} homes): "
            f"{EXACT_ROW} reads the true receptacles of the last {history} h up to τ, hidden "
            f"hours included, its favourites unknown; {FILTER_ROW} knows every object's law and "
            f"filters over the observed hours only.")
    return rows, note, np.asarray(REGIMES)[regime]
