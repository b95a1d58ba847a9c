"""Object search with a placement prior: look at a table, fail, update the belief, look again.

A robot searches the tables of the object's kind for it. Each look drives to a table (Euclidean
travel between box centres, pixels) and finds the object if it is there (missing it with
probability ``p_miss``); after every failed look the belief is updated by Bayes' rule and the
policy re-plans. FlowSim's exact posterior drives the Bayes-optimal searcher, so every prior —
FlowMaps, the MLP baseline, uniform over the kind, last-seen — is scored against the optimum.
The protocol is documented in docs/search.md.

    from flowmaps_jax import search
    probs = search.table_probabilities(predictor, tokens, queries, 100, jax.random.key(0))
    # (B, Q, S + 1): mass on each table token, then "off"; search.table_dict(probs, tokens)
    s = search.build_search_set(scenes, config, jax.random.key(0))
    episodes, _ = search.make_episodes(s, search.exact_tables(s))
    outcome = search.run_episodes(episodes, "optimal")
    scores = search.episode_scores(outcome)            # sr@1..3, looks, travel, spl per episode

Modules: ``probabilities`` (table probabilities of the exact priors, plain-dict form; a model's
are :mod:`flowmaps_jax.tables`, below the predictor), ``policies``
(most-probable, greedy, exact optimal DP, nearest), ``simulator`` (episodes, Bayes update, the
jitted episode loop: no FlowSim), ``episodes`` (the FlowSim search set, its priors and the
episodes they make), ``scores`` (SR@k, looks, travel, SPL, ratios), ``protocol`` (every prior
by every policy), ``report`` and ``figures`` (JSON, Markdown, figures) and ``cli``
(``python -m flowmaps_jax.search``).
"""

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
from flowmaps_jax.search.policies import (
    MAX_OPTIMAL_TABLES,
    POLICIES,
    optimal_expected_travel,
    plan_costs,
)
from flowmaps_jax.search.probabilities import slots_to_tables, table_dict
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
    "slots_to_tables",
    "spl",
    "success_curves",
    "summarise_scores",
    "table_boxes",
    "table_dict",
    "table_probabilities",
    "truth_probs",
    "uniform_tables",
]
