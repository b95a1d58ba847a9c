"""Object search with a placement prior: look at a table, fail, update the belief, look again
(the protocol: docs/search.md).

    from flowmaps_jax import search
    probs = search.table_probabilities(predictor, tokens, queries, 100, jax.random.key(0))
    s = search.build_search_set(scenes, config, jax.random.key(0))
    episodes, _ = search.make_episodes(s, search.exact_tables(s))
    scores = search.episode_scores(search.run_episodes(episodes, "optimal"))
"""

from flowmaps_jax.navigation.policies import (
    MAX_OPTIMAL_TABLES,
    POLICIES,
    optimal_expected_travel,
    plan_costs,
)
from flowmaps_jax.search.episodes import (
    STARTS,
    SearchSet,
    build_search_set,
    exact_tables,
    last_seen_tables,
    make_episodes,
    predictor_tables,
    truth_probs,
    uniform_tables,
)
from flowmaps_jax.search.probabilities import table_dict
from flowmaps_jax.search.scores import (
    SCORES,
    episode_scores,
    expected_scores,
    ratios,
    spl,
    success_curves,
    summarise_scores,
)
from flowmaps_jax.search.simulator import (
    DEFAULT_BUDGET,
    Episodes,
    Outcome,
    at_targets,
    bayes_update,
    expected_outcomes,
    run_episodes,
    simulate,
)
from flowmaps_jax.tables import ASSIGN_TOLERANCE, table_boxes, table_probabilities

__all__ = [
    "ASSIGN_TOLERANCE",
    "DEFAULT_BUDGET",
    "MAX_OPTIMAL_TABLES",
    "POLICIES",
    "SCORES",
    "STARTS",
    "Episodes",
    "Outcome",
    "SearchSet",
    "at_targets",
    "bayes_update",
    "build_search_set",
    "episode_scores",
    "exact_tables",
    "expected_outcomes",
    "expected_scores",
    "last_seen_tables",
    "make_episodes",
    "optimal_expected_travel",
    "plan_costs",
    "predictor_tables",
    "ratios",
    "run_episodes",
    "simulate",
    "spl",
    "success_curves",
    "summarise_scores",
    "table_boxes",
    "table_dict",
    "table_probabilities",
    "truth_probs",
    "uniform_tables",
]
