"""FlowMaps on FlowSim homes: queries, tokens, the homes model, reference priors and navigation.

The simulator and the exact posterior live in :mod:`flowmaps_jax.flowsim.homes`; this package is
the model side. Every prior (exact, FlowMaps, the reference rows) is a function
``prior(homes, queries) -> (E, Q, R)`` probabilities over each home's receptacle slots
(:mod:`.queries`), so the evaluation and the navigation scores treat them alike.
"""

from flowmaps_jax.homes.queries import DEFAULT_HORIZONS, HomesQueries, draw_queries

__all__ = ["DEFAULT_HORIZONS", "HomesQueries", "draw_queries"]
