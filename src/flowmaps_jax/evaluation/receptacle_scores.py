"""Posterior scores of a prior against the exact posterior per query (p, q (..., R) over
receptacle slots): ``kl`` in nats (p floored at ``KL_FLOOR``), and the 2-D slot metrics' ``tv``,
``top1`` and ``rank_cost`` (docs/protocol.md) with the off bin 1 − Σ_r p_r; :func:`summarise`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.evaluation import report
from flowmaps_jax.evaluation.priors import allowed_slots
from flowmaps_jax.evaluation.slots import score_slots
from flowmaps_jax.flowsim.homes import REGIMES, HomesConfig
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.flowsim.homes.world import Homes
from flowmaps_jax.validation import check_array, check_instance

KL_FLOOR = 1e-9
"""KL(q ‖ p) reads max(p, KL_FLOOR): about 20.7 nats per unit of q's mass where p has none."""
POSTERIOR_METRICS = ("kl", "tv", "top1", "rank_cost")
REFERENCE_TOLERANCE = 1e-3
"""How far from 1 a reference posterior's row may sum (float32 rounding of R² hourly steps)."""
ASSIGN_MARGIN = 0.1
"""Metres: a sampled box counts for a receptacle within half its footprint diagonal plus this."""


@jax.jit
def _kl(p, q, allowed):
    p, q = jnp.where(allowed, p, 0.0), jnp.where(allowed, q, 0.0)
    return jnp.sum(jnp.where(q > 0, q * (jnp.log(jnp.where(q > 0, q, 1.0))
                                         - jnp.log(jnp.maximum(p, KL_FLOOR))), 0.0), axis=-1)


@jax.jit
def _with_off_bin(p, allowed):
    """p (..., R) on the allowed receptacles, then its off mass: the 2-D slots' layout."""
    p = jnp.where(allowed, p, 0.0)
    return jnp.concatenate([p, jnp.clip(1.0 - jnp.sum(p, axis=-1, keepdims=True), 0.0, 1.0)],
                           axis=-1)


def check_reference(q, tolerance: float = REFERENCE_TOLERANCE) -> None:
    """``ValueError`` unless every row of the reference posterior q (..., R) is finite and sums to
    1 within ``tolerance``."""
    total = np.asarray(jnp.sum(q, axis=-1))
    bad = ~np.isfinite(total) | (np.abs(total - 1.0) > tolerance)
    if np.any(bad):
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"q: the reference posterior's row {where} sums to {total[where]:.12g}, "
                         f"not 1 ({int(bad.sum())} of {bad.size} rows): its scores would be "
                         f"wrong, so none are computed")


def posterior_scores(p, q, allowed) -> dict[str, jax.Array]:
    """{``kl``, ``tv``, ``top1``, ``rank_cost``} (...) of p (..., R) against q (..., R) on the
    ``allowed`` (..., R) receptacles (see the module's docstring)."""
    shape = tuple(check_array("q", q, (..., None)).shape)  # (..., R): the others' shape
    check_array("p", p, shape)
    check_array("allowed", allowed, shape)
    p, allowed = jnp.asarray(p, jnp.float32), jnp.asarray(allowed, bool)
    q = jnp.where(allowed, jnp.asarray(q, jnp.float32), 0.0)
    check_reference(q)
    slots = score_slots(_with_off_bin(p, allowed), q, allowed)  # TV, top-1, rank cost
    return {"kl": _kl(p, q, allowed), "tv": slots["tv"], "top1": slots["top1"],
            "rank_cost": slots["search_cost_ratio"]}


def object_positions(homes: Homes, queries: HomesQueries, config: HomesConfig) -> jax.Array:
    """(E, Q, R, 3): the centre (x, y, z) the queried object's box would have on each
    receptacle (on its top, as ``flowsim.homes.object_boxes`` places it)."""
    size = jnp.asarray([o.size for o in config.object_classes], jnp.float32)
    cls = jnp.take_along_axis(homes.object_class, queries.object_index, axis=1)
    height = size[jnp.maximum(cls, 0), 2]  # (E, Q)
    box = homes.receptacle_box[:, None]  # (E, 1, R, 6)
    top = box[..., 2] + box[..., 5] / 2
    z = top + height[..., None] / 2
    return jnp.stack([jnp.broadcast_to(box[..., 0], z.shape),
                      jnp.broadcast_to(box[..., 1], z.shape), z], axis=-1)


@jax.jit
def _assign(samples, positions, allowed, footprint):
    centre = samples[..., None, :3]  # (E, Q, N, 1, 3)
    dist = jnp.linalg.norm(centre - positions[:, :, None], axis=-1)  # (E, Q, N, R)
    dist = jnp.where(allowed[:, :, None], dist, jnp.inf)
    nearest = jnp.argmin(dist, axis=-1)
    radius = jnp.take_along_axis(jnp.broadcast_to(footprint[:, None, None], dist.shape),
                                 nearest[..., None], axis=-1)[..., 0]
    inside = jnp.min(dist, axis=-1) <= radius
    hits = (nearest[..., None] == jnp.arange(dist.shape[-1])) & inside[..., None]
    return jnp.mean(hits, axis=-2, dtype=jnp.float32)


def assign_samples(samples, homes: Homes, queries: HomesQueries,
                   config: HomesConfig) -> jax.Array:
    """(E, Q, R) fractions of sampled boxes (E, Q, N, 6) on each allowed receptacle (the nearest
    object position, off beyond half its footprint diagonal plus ``ASSIGN_MARGIN``)."""
    check_instance("queries", queries, HomesQueries)
    e, q = check_array("queries.object_index", queries.object_index, (None, None)).shape
    check_array("samples", samples, (e, q, None, 6))
    box = homes.receptacle_box
    footprint = 0.5 * jnp.hypot(box[..., 3], box[..., 4]) + ASSIGN_MARGIN  # (E, R)
    return _assign(jnp.asarray(samples, jnp.float32), object_positions(homes, queries, config),
                   allowed_slots(homes, queries), footprint)


# --------------------------------------------------------------------------- summaries


def _json(x: float) -> float | None:
    return float(f"{x:.6g}") if math.isfinite(x) else None


def _rounded(summary: dict) -> dict:
    """A :func:`flowmaps_jax.evaluation.report.summarise` entry, JSON-safe (6 digits; NaN →
    None)."""
    return {"mean": _json(summary["mean"]), "stderr": _json(summary["stderr"]),
            "count": int(summary["count"])}


def stats(values) -> dict:
    """{mean, stderr, count} of per-query values (stderr None for fewer than two; JSON-safe):
    the one summary (:func:`flowmaps_jax.evaluation.report.summarise`), rounded."""
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0:
        return {"mean": None, "stderr": None, "count": 0}
    return _rounded(report.summarise(v)["overall"])


def query_groups(homes: Homes, queries: HomesQueries) -> dict[str, np.ndarray]:
    """{"regime": (E, Q) regime names, "horizon": (E, Q) τ_q − τ} of every query."""
    regime = np.take_along_axis(np.asarray(homes.regime), np.asarray(queries.object_index), 1)
    return {"regime": np.asarray(REGIMES)[regime], "horizon": np.asarray(queries.horizon)}


def summarise(values, groups: dict[str, np.ndarray]) -> dict:
    """{"overall": stats, "by_<group>": {id: stats}} of per-query values (E, Q); ids as
    strings, regimes in ``REGIMES`` order, horizons ascending."""
    v = np.asarray(values, np.float64)
    out = {"overall": stats(v)}
    for name, labels in groups.items():
        by_group = report.summarise(v, np.asarray(labels))["by_group"]
        out[f"by_{name}"] = {str(i): _rounded(by_group[i]) for i in group_ids(name, labels)}
    return out


def group_ids(name: str, labels) -> list:
    """The ids present in a group's labels: regimes in ``REGIMES`` order, others ascending."""
    labels = np.asarray(labels)
    return [r for r in REGIMES if np.any(labels == r)] if name == "regime" else \
        sorted(np.unique(labels).tolist())


def best_rows(table: dict, names, metric: str, group: str, higher: bool) -> dict:
    """{"overall" and each id of ``by_<group>``: {"row": name, ``metric``: mean}}: the best
    mean ``metric`` among the rows ``names`` of a results ``table`` (name -> {"metrics": …})."""
    best: dict = {}
    for name in names:
        summary = table[name]["metrics"][metric]
        for key, stat in {"overall": summary["overall"], **summary[f"by_{group}"]}.items():
            if stat["mean"] is not None and (key not in best or (
                    stat["mean"] > best[key][metric] if higher else
                    stat["mean"] < best[key][metric])):
                best[key] = {"row": name, metric: stat["mean"]}
    return best


def best_lines(best: dict, title: str, metric: str) -> list[str]:
    """The markdown of :func:`best_rows`' answer: a titled table, one line per group."""
    lines = [title, "", f"| | best reference row | {metric} |", "|---|---|---|"]
    return lines + [f"| {k} | {v['row']} | {v[metric]:.3f} |" for k, v in best.items()] + [""]
