# ruff: noqa: I001  (the imports are the README block's, as written there)
"""The README quick start, as a script: samples the pretrained FlowMaps for the fork one step ahead.

    python experiments/quickstart.py        # writes fork_next.png in the current directory

The code below is the README's quick-start block, line for line (tests/test_pretrained.py checks
that they agree and runs the README block itself). docs/figures/quickstart_fork.png is drawn by
``python experiments/render_docs_figures.py``, which runs the README block too.
"""
import jax
import numpy as np
from flowmaps_jax.flowsim import exact_posterior, render
from flowmaps_jax.flowsim.scenes import scene_tokens, validation_split
from flowmaps_jax.predictor import load_pretrained
from flowmaps_jax.tokens import Queries

predictor = load_pretrained("flowmaps")            # packaged with flowmaps-jax (8.9 MB)
config = predictor.flowsim
scenes = validation_split(config, num_envs=1)      # a held-out FlowSim home
env, fork, tau, tau_q = 0, 0, 5, 6                 # where is the fork one step after τ = 5?
tokens = scene_tokens(scenes, np.array([env]), np.array([tau]), config)
queries = Queries(descriptor=np.asarray(scenes.object_kind)[:1, :1], tau_q=np.array([[tau_q]]))
boxes = predictor.sample(tokens, queries, num_samples=100, key=jax.random.key(0))  # (1, 1, 100, 4)

q = exact_posterior(scenes.num_slots[env, fork], scenes.slot[env, tau, fork], tau_q - tau, config)
fig = render.draw_posterior(scenes, env, fork, tau, q, config)   # red shading: the exact answer
render.overlay_boxes(fig.axes[0], boxes[0, 0], config, label="FlowMaps samples")  # black outlines
fig.savefig("fork_next.png", dpi=130)
