"""Routine diagnostic: does a predictor know *which* table comes next, not only which kind? Two
small fixed query sets (one step ahead, and the horizon mixture); the mass at route offsets and
the slot scores become the ``"routine"`` records of ``metrics.jsonl``.
"""

from __future__ import annotations

import json
import pathlib

import jax
import numpy as np
from flax import struct
from matplotlib.figure import Figure

from flowmaps_jax.evaluation.protocol import (
    EvalSet,
    build_eval_queries,
    scores_against_q,
    slot_shares,
)
from flowmaps_jax.evaluation.slots import ROUTE_OFFSET_LABELS, offset_mass
from flowmaps_jax.flowsim.scenes import scene_tokens
from flowmaps_jax.validation import check_instance, check_int

EXACT_ONE_STEP = (0.2, 0.7, 0.1, 0.0, 0.0, 0.0)
"""The exact posterior's route-offset mass one step ahead (FlowSim's Markov dynamics)."""


@struct.dataclass
class RoutineProbe:
    """Fixed query sets for the diagnostic: ``one_step`` (Δτ = 1) and ``mixed``."""

    one_step: EvalSet
    mixed: EvalSet


def build_probe(scenes, config, num_envs: int = 20, seed: int = 0,
                history: int = 1) -> RoutineProbe:
    """The probe from the first ``num_envs`` environments of ``scenes`` (3 queries each), for a
    model reading the last ``history`` maps."""
    num_envs = check_int("num_envs", num_envs)
    if num_envs > scenes.num_envs:
        raise ValueError(f"num_envs must be <= {scenes.num_envs} (the environments in scenes); "
                         f"got {num_envs}")
    history = check_int("history", history, 1, config.num_timesteps)
    part = jax.tree_util.tree_map(lambda a: a[:num_envs], scenes)
    key = jax.random.key(seed)

    def query_set(salt: int, horizon: int | None) -> EvalSet:
        evalset = build_eval_queries(part, config, jax.random.fold_in(key, salt), 2,
                                     horizon=horizon, history=history)
        if history == 1:
            return evalset
        return evalset.replace(tokens=scene_tokens(part, evalset.env, evalset.tau, config,
                                                   history=history))

    return RoutineProbe(one_step=query_set(1, 1), mixed=query_set(2, None))


def routine_metrics(predictor, probe: RoutineProbe, key: jax.Array | None = None,
                    num_samples: int = 32) -> dict[str, float]:
    """Sample ``predictor`` on the probe: floats ``offset_0`` … ``offset_+3``, ``offset_beyond``,
    ``offset_off``, ``one_step_{tv,top1,search_cost_ratio}`` and ``tv``, ``top1``,
    ``search_cost_ratio`` (horizon mixture)."""
    check_instance("probe", probe, RoutineProbe)
    num_samples = check_int("num_samples", num_samples)
    key = jax.random.key(0) if key is None else key
    out: dict[str, float] = {}
    for i, (label, evalset) in enumerate((("one_step", probe.one_step), ("mixed", probe.mixed))):
        samples = predictor.sample(evalset.tokens, evalset.queries, num_samples,
                                   jax.random.fold_in(key, i))
        # the probe's arrays were built by build_eval_queries: the slot kernels, no re-check
        p_hat = slot_shares(evalset, samples)
        scores = {k: float(np.mean(v)) for k, v in scores_against_q(evalset, p_hat).items()}
        if label == "one_step":
            mass = np.asarray(offset_mass(p_hat, evalset.slot_now,
                                          evalset.num_slots)).mean(axis=(0, 1))
            out.update({f"offset_{name}": float(m)
                        for name, m in zip(ROUTE_OFFSET_LABELS, mass, strict=True)})
            out.update({f"one_step_{k}": v for k, v in scores.items()})
        else:
            out.update(scores)
    return out


def read_routine_records(metrics_path: str | pathlib.Path) -> list[dict]:
    """The ``"kind": "routine"`` records of a run's metrics.jsonl, in order."""
    path = pathlib.Path(metrics_path)
    if path.is_dir():
        path = path / "metrics.jsonl"
    if not path.is_file():
        raise ValueError(f"metrics_path: no metrics.jsonl at {path}")
    records = []
    for line in path.read_text().splitlines():
        if line.strip():
            record = json.loads(line)
            if record.get("kind") == "routine":
                records.append(record)
    return records


def plot_learning_curve(records: list[dict], title: str = "") -> Figure:
    """Route-offset mass one step ahead, and TV / rank cost, against the training step."""
    if not records:
        raise ValueError("records: no routine records to plot (was the run validated?)")
    steps = [r["step"] for r in records]
    fig = Figure(figsize=(10, 3.6))
    ax_mass, ax_slot = fig.subplots(1, 2)
    colours = ("tab:grey", "tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:red")
    for name, exact, colour in zip(ROUTE_OFFSET_LABELS, EXACT_ONE_STEP, colours, strict=True):
        if name in ("+3", "beyond"):
            continue
        ax_mass.plot(steps, [r[f"offset_{name}"] for r in records], color=colour,
                     label=f"offset {name}", marker=".")
        if exact > 0:
            ax_mass.axhline(exact, color=colour, linestyle=":", linewidth=1)
    ax_mass.set(xlabel="training step", ylabel="sample mass", ylim=(0, 1),
                title="one step ahead (dotted: exact)")
    ax_mass.legend(fontsize=8)
    for key, label, colour in (("tv", "slot TV (mixed Δτ)", "tab:blue"),
                               ("one_step_tv", "slot TV (Δτ = 1)", "tab:cyan"),
                               ("search_cost_ratio", "rank cost − 1", "tab:red")):
        values = [r[key] - (1.0 if key == "search_cost_ratio" else 0.0) for r in records]
        ax_slot.plot(steps, values, label=label, color=colour, marker=".")
    ax_slot.set(xlabel="training step", ylim=(0, None), title="slot metrics (lower is better)")
    ax_slot.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
