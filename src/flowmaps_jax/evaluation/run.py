"""The whole evaluation in one call (behind ``python -m flowmaps_jax.evaluate``): queries,
reference rows, each predictor, report and figures. Each model reads the maps it was trained on;
``history`` H is what the exact reference posterior is given.
"""

from __future__ import annotations

import dataclasses
import pathlib
import time
from collections.abc import Sequence

import jax

from flowmaps_jax.atomic_files import make_output_dir, save_figure
from flowmaps_jax.evaluation.figures import plot_by_horizon, plot_kl, plot_samples, plot_slot_bars
from flowmaps_jax.evaluation.protocol import (
    DEFAULT_CHUNK_ENVS,
    DEFAULT_KL_DRAWS,
    DEFAULT_LIKELIHOOD_DRAWS,
    DEFAULT_LIKELIHOOD_STEPS,
    DEFAULT_SAMPLES,
    ERROR_ENVS,
    EvalSet,
    RowResult,
    build_eval_queries,
    evaluate_predictor,
    reference_rows,
)
from flowmaps_jax.evaluation.report import summarise_habits, summarise_rows, write_report
from flowmaps_jax.flowsim import habits
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.scenes import check_history, scene_tokens
from flowmaps_jax.flowsim.worlds import world_of
from flowmaps_jax.predictor import DEFAULT_NUM_STEPS, Predictor
from flowmaps_jax.tables import ASSIGN_RADIUS
from flowmaps_jax.validation import check_instance, check_output_dir

REPORT_FILES = ("results.json", "results.md")
FIGURES = ("kl.png", "by_horizon.png", "samples.png", "slots.png")
"""The files an evaluation writes into its ``out_dir`` (figures unless ``figures=False``)."""


def run_evaluation(predictors: Sequence[Predictor], scenes, config: FlowSimConfig,
                   out_dir: str | pathlib.Path | None = None, *, seed: int = 0,
                   sample_counts: Sequence[int] = DEFAULT_SAMPLES,
                   kl_draws: int = DEFAULT_KL_DRAWS, chunk_envs: int = DEFAULT_CHUNK_ENVS,
                   num_steps: int = DEFAULT_NUM_STEPS, method: str = "midpoint",
                   logp_steps: int | None = None,
                   likelihood_steps: int | None = DEFAULT_LIKELIHOOD_STEPS,
                   likelihood_draws: int = DEFAULT_LIKELIHOOD_DRAWS, figures: bool = True,
                   progress: bool = True, history: int | None = None,
                   ) -> tuple[dict, list[RowResult], EvalSet]:
    """Evaluate ``predictors`` (in report order) on every environment of ``scenes``, writing
    the report and figures into ``out_dir`` if given; a flow's KL uses the accurate likelihood
    on ``likelihood_steps`` grid points (None: the paper's grid only). Every argument is checked
    first. Returns (the results.json dict, the RowResults, the EvalSet).
    """
    if not isinstance(predictors, (tuple, list)) or not predictors:
        raise ValueError(f"predictors must be a tuple of Predictor objects; got {predictors!r}")
    predictors = tuple(check_instance("predictors", p, Predictor) for p in predictors)
    for p in predictors:
        if p.flowsim.map_size != config.map_size or p.flowsim.categories != config.categories:
            raise ValueError(f"predictor {p.name} ({p.source}) was trained on a different FlowSim "
                             "config (map size or categories) than the evaluation scenes")
    history = default_history(predictors, config) if history is None else history
    for p in predictors:
        if p.model.history > 1:
            check_history(p.model.history, model_token_config(config, p))
    if out_dir is not None:  # before anything runs: a file there, or a link at a report's name
        check_output_dir("out_dir", out_dir, files=[*REPORT_FILES, *(FIGURES if figures else ())])
    start = time.perf_counter()
    key = jax.random.key(seed)
    evalset = build_eval_queries(scenes, config, key, kl_draws, history=history)
    rows = reference_rows(evalset, sample_counts, key)
    with_history = evalset.habit is not None
    names = unique_names([f"{p.name} (H = {p.model.history})" if with_history else p.name
                          for p in predictors])
    for predictor, name in zip(predictors, names, strict=True):
        view = model_view(evalset, scenes, config, predictor)
        rows.append(evaluate_predictor(
            predictor, view, key, sample_counts, chunk_envs, num_steps, method, logp_steps,
            progress, name, likelihood_steps, likelihood_draws))
    # as the rows checked them
    counts = sorted(int(n) for n in sample_counts)
    num_steps, logp_steps = int(num_steps), int(num_steps if logp_steps is None else logp_steps)
    if likelihood_steps is not None:
        likelihood_steps = int(likelihood_steps)
    results = {
        "protocol": {"num_envs": evalset.num_envs, "objects_per_env": config.num_objects,
                     "num_queries": evalset.num_queries, "samples": list(counts),
                     "kl_draws": kl_draws, "num_steps": num_steps, "method": method,
                     "logp_steps": logp_steps, "likelihood_steps": likelihood_steps,
                     "likelihood_draws": min(likelihood_draws, kl_draws),
                     "integration_error_envs": ERROR_ENVS,
                     "seed": seed, "assignment": "v2", "assign_radius": ASSIGN_RADIUS,
                     "dynamics": config.dynamics},
        "rows": summarise_rows(rows, evalset, config),
        "figures": [],
    }
    if with_history:  # only then: the paper's report keeps its exact keys
        results["protocol"].update(world=world_of(config) or "custom", history=evalset.history,
                                   habits=[list(h) for h in config.habits])
        results["by_habit"] = summarise_habits(rows, evalset)
    if out_dir is not None:
        out = make_output_dir("out_dir", out_dir)
        if figures:
            model_rows = [r for r in rows if r.samples is not None]
            plots = {FIGURES[0]: lambda: plot_kl(results),
                     FIGURES[1]: lambda: plot_by_horizon(results),
                     FIGURES[2]: lambda: plot_samples(scenes, evalset, model_rows, config),
                     FIGURES[3]: lambda: plot_slot_bars(evalset, model_rows, config)}
            for filename, make in plots.items():
                save_figure(make(), out / filename, name="out_dir file", dpi=110)
                results["figures"].append(filename)
        results["seconds"] = round(time.perf_counter() - start, 1)
        write_report(results, out)
    else:
        results["seconds"] = round(time.perf_counter() - start, 1)
    return results, rows, evalset


def default_history(predictors: Sequence[Predictor], config: FlowSimConfig) -> int:
    """The observations the exact posterior is given by default
    (``flowsim.habits.default_history`` of the most maps any of ``predictors`` reads)."""
    return habits.default_history(config, max((p.model.history for p in predictors), default=1))


def model_token_config(config: FlowSimConfig, predictor: Predictor) -> FlowSimConfig:
    """The evaluation ``config`` with the token count the predictor was trained on."""
    if predictor.flowsim.max_tokens == config.max_tokens:
        return config
    return dataclasses.replace(config, max_tokens=predictor.flowsim.max_tokens)


def model_view(evalset: EvalSet, scenes, config: FlowSimConfig,
               predictor: Predictor) -> EvalSet:
    """``evalset`` with the tokens ``predictor`` reads (the last h maps of ``model.history``);
    queries and ground truth unchanged."""
    h = predictor.model.history
    if h == 1 and predictor.flowsim.max_tokens >= config.max_tokens:
        return evalset
    tokens = scene_tokens(scenes, evalset.env, evalset.tau,
                          model_token_config(config, predictor), history=h)
    return evalset.replace(tokens=tokens)


def unique_names(names: Sequence[str]) -> list[str]:
    """Row labels made unique by a " #2", " #3" suffix on repeats."""
    seen: dict[str, int] = {}
    out = []
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f"{n} #{seen[n]}")
    return out
