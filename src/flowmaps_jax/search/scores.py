"""Search metrics over a batch of episodes, overall and by group, and ratios between rows
(docs/search.md, "Metrics"): per episode ``sr@k`` (k = 1, 2, 3), ``looks``, ``travel`` (pixels),
``spl`` and ``found``; a ratio is a row's mean over the exact-posterior row's, same policy.
"""

from __future__ import annotations

import math

import numpy as np

from flowmaps_jax.evaluation.report import summarise

SR_LOOKS = (1, 2, 3)
SCORES = ("sr@1", "sr@2", "sr@3", "looks", "travel", "spl", "found")


def spl(found, shortest, travel) -> np.ndarray:
    """Success weighted by path length (...): found · ℓ / max(p, ℓ); 1 if found with ℓ = p = 0.
    Host-side numpy (a score of finished episodes)."""
    found = np.asarray(found, bool)
    shortest, travel = np.asarray(shortest, np.float64), np.asarray(travel, np.float64)
    longest = np.maximum(shortest, travel)
    ratio = np.where(longest > 0, shortest / np.where(longest > 0, longest, 1.0), 1.0)
    return np.where(found, ratio, 0.0)


def episode_scores(outcome) -> dict[str, np.ndarray]:
    """Per-episode scores of an Outcome (any leading shape ...): each in ``SCORES`` (...), float64,
    plus ``success_at`` (..., L): found within k = 1..L looks."""
    found = np.asarray(outcome.found, bool)
    looks = np.asarray(outcome.looks)
    budget = np.shape(outcome.path)[-1]
    within = found[..., None] & (looks[..., None] <= np.arange(1, budget + 1))
    out = {f"sr@{k}": within[..., min(k, budget) - 1].astype(np.float64) for k in SR_LOOKS}
    out.update(looks=looks.astype(np.float64), travel=np.asarray(outcome.travel, np.float64),
               spl=spl(found, outcome.shortest, outcome.travel),
               found=found.astype(np.float64), success_at=within.astype(np.float64))
    return out


def expected_scores(outcome, weights) -> dict[str, np.ndarray]:
    """Scores averaged over where the object hides: ``outcome`` with a leading (K, N) axis and
    ``weights`` (K, N) (from ``simulator.expected_outcomes``) → each score (N,) (or (N, L))."""
    scores = episode_scores(outcome)
    w = np.asarray(weights, np.float64)
    return {name: np.einsum("kn,kn...->n...", w, value) for name, value in scores.items()}


# --------------------------------------------------------------------------- aggregation


def _json(x: float) -> float | None:
    """A JSON number to 4 significant digits (None for NaN / inf)."""
    return float(f"{x:.4g}") if math.isfinite(x) else None


def _stat(summary: dict) -> dict:
    return {"mean": _json(summary["mean"]), "stderr": _json(summary["stderr"])}


def mean_stat(values) -> dict:
    """{mean, stderr, count} of any per-episode values (JSON-safe)."""
    summary = summarise(np.asarray(values, np.float64))["overall"]
    return {**_stat(summary), "count": int(summary["count"])}


def summarise_scores(scores: dict[str, np.ndarray],
                     groups: dict[str, np.ndarray] | None = None) -> dict:
    """{"overall": {"count": n, score: {mean, stderr}}, "by_<group>": {id: {"count": n,
    score: ...}}} of :func:`episode_scores`; ``groups``: {name: labels (N,)}. JSON-safe."""
    out: dict = {"overall": {"count": int(np.size(scores[SCORES[0]]))}}
    for name in SCORES:
        out["overall"][name] = _stat(summarise(scores[name])["overall"])
    for group, labels in (groups or {}).items():
        by: dict = {}
        for name in SCORES:
            split = summarise(scores[name], np.asarray(labels))["by_group"]
            for gid, stat in split.items():
                by.setdefault(str(gid), {"count": int(stat["count"])})[name] = _stat(stat)
        out[f"by_{group}"] = by
    return out


def ratios(summary: dict, reference: dict) -> dict:
    """Each mean of ``summary`` over the same mean of ``reference`` (both from
    :func:`summarise_scores`, same groups); None where the reference mean is 0 or missing."""
    def divide(a: dict, b: dict) -> dict:
        out = {}
        for name in SCORES:
            top, bottom = a[name]["mean"], (b.get(name) or {}).get("mean")
            out[name] = None if top is None or not bottom else round(top / bottom, 4)
        return out

    result = {}
    for part, table in summary.items():
        if part == "overall":
            result[part] = divide(table, reference[part])
        else:
            result[part] = {gid: divide(v, reference[part].get(gid, {})) for gid, v in
                            table.items()}
    return result


def success_curves(scores: dict[str, np.ndarray], distance_grid) -> dict:
    """Success rate within k looks (k = 1..L) and within d pixels driven (d in distance_grid):
    {"looks": [...L], "distance": {"d": [...], "success": [...]}}."""
    grid = np.asarray(distance_grid, np.float64)
    within = (scores["found"][:, None] > 0) & (scores["travel"][:, None] <= grid[None] + 1e-6)
    return {"looks": np.round(scores["success_at"].mean(0), 4).tolist(),
            "distance": {"d": np.round(grid, 1).tolist(),
                         "success": np.round(within.mean(0), 4).tolist()}}
