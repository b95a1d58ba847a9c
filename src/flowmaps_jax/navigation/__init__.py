"""Search policies and the homes navigation, below both evaluation and search.

``policies``: which table to look at next (most-probable, greedy, the exact subset DP, nearest),
for one episode, pure and jit-able. ``navigation``: object navigation in FlowSim homes (geodesic
starts, visiting orders, walked episodes, SR@k / SPL). Neither imports evaluation or search.
"""
