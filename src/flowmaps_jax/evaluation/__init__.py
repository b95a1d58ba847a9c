"""Evaluation against the exact posterior (the protocol: docs/protocol.md; the module map:
docs/design.md). :func:`run.run_evaluation` runs the 2-D protocol in one call; ``cli`` is
``python -m flowmaps_jax.evaluate``.
"""

from flowmaps_jax.evaluation.figures import (
    pick_queries,
    plot_by_horizon,
    plot_kl,
    plot_samples,
    plot_slot_bars,
)
from flowmaps_jax.evaluation.kl import (
    Estimate,
    continuous_kl,
    gt_mixture_log_prob,
    gt_mixture_sigma,
    sample_gt_mixture,
)
from flowmaps_jax.evaluation.priors import (
    last_seen_slots,
    oracle_slots,
    sampled_oracle_slots,
    uniform_slots,
)
from flowmaps_jax.evaluation.protocol import (
    DEFAULT_CHUNK_ENVS,
    DEFAULT_KL_DRAWS,
    DEFAULT_LIKELIHOOD_STEPS,
    DEFAULT_NUM_ENVS,
    DEFAULT_SAMPLES,
    REFERENCE_ROWS,
    EvalSet,
    RowResult,
    build_eval_queries,
    evaluate_predictor,
    history_row_names,
    reference_rows,
)
from flowmaps_jax.evaluation.report import (
    markdown_table,
    summarise,
    summarise_habits,
    summarise_rows,
    write_report,
)
from flowmaps_jax.evaluation.routine import (
    RoutineProbe,
    build_probe,
    plot_learning_curve,
    read_routine_records,
    routine_metrics,
)
from flowmaps_jax.evaluation.run import default_history, run_evaluation
from flowmaps_jax.evaluation.slots import (
    ROUTE_OFFSET_LABELS,
    SLOT_METRICS,
    route_offset_mass,
    slot_scores,
)
from flowmaps_jax.tables import ASSIGN_RADIUS, empirical_slots  # the protocol's assignment

__all__ = [
    "ASSIGN_RADIUS",
    "DEFAULT_CHUNK_ENVS",
    "DEFAULT_KL_DRAWS",
    "DEFAULT_LIKELIHOOD_STEPS",
    "DEFAULT_NUM_ENVS",
    "DEFAULT_SAMPLES",
    "REFERENCE_ROWS",
    "ROUTE_OFFSET_LABELS",
    "SLOT_METRICS",
    "Estimate",
    "EvalSet",
    "RoutineProbe",
    "RowResult",
    "build_eval_queries",
    "build_probe",
    "continuous_kl",
    "default_history",
    "empirical_slots",
    "evaluate_predictor",
    "gt_mixture_log_prob",
    "gt_mixture_sigma",
    "history_row_names",
    "last_seen_slots",
    "markdown_table",
    "oracle_slots",
    "pick_queries",
    "plot_by_horizon",
    "plot_kl",
    "plot_learning_curve",
    "plot_samples",
    "plot_slot_bars",
    "read_routine_records",
    "reference_rows",
    "route_offset_mass",
    "routine_metrics",
    "run_evaluation",
    "sample_gt_mixture",
    "sampled_oracle_slots",
    "slot_scores",
    "summarise",
    "summarise_habits",
    "summarise_rows",
    "uniform_slots",
    "write_report",
]
