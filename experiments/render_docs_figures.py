"""Regenerate the figures committed under docs/figures/ (deterministic: fixed seeds).

    python experiments/render_docs_figures.py [--out docs/figures]

Writes flowsim_scene.png, flowsim_timeline.png, flowsim_orders.png and flowsim_posterior.png.
The environment shown is the first of a fixed batch whose first three transitions include a
stay, a one-place advance and a two-place skip, so the timeline shows every kind of move.
It also writes quickstart_fork.png by running the README's quick-start block itself (the pretrained
FlowMaps), so the README's figure is exactly what its code draws.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import tempfile
from pathlib import Path

import jax
import numpy as np

from flowmaps_jax.flowsim import render
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.dynamics import exact_posterior
from flowmaps_jax.flowsim.generate import generate

SEED = 0
NUM_CANDIDATES = 32
TIMELINE = (0, 1, 2, 3)
POSTERIOR_OBJECT, POSTERIOR_TAU, POSTERIOR_HORIZON = 0, 3, 3  # fork, seen at τ=3, asked at τ=6
DPI = 130
# No "Software" key and no timestamp, so re-running the script gives byte-identical files.
PNG_METADATA = {"Software": None}
README = Path(__file__).resolve().parents[1] / "README.md"


def quickstart_figure(out: Path) -> Path:
    """Run the README's quick-start block in a scratch directory and copy the figure it saves
    (fork_next.png) to ``out / "quickstart_fork.png"``."""
    section = README.read_text().split("## Quick start")[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    target = out.resolve() / "quickstart_fork.png"
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        try:
            exec(compile(code, "README quick start", "exec"), {})
        finally:
            os.chdir(cwd)
        shutil.copyfile(Path(scratch) / "fork_next.png", target)
    return target


def pick_environment(scenes, config: FlowSimConfig) -> int:
    """First environment whose moves over TIMELINE include a stay, a +1 and a +2, and whose
    angular visiting orders are spread out (consecutive tables at least 50° apart), so the
    arrows of the orders figure do not run over each other."""
    slot = np.asarray(scenes.slot)[:, list(TIMELINE)]  # (E, len, M)
    k = np.asarray(scenes.num_slots)[:, None, :]
    steps = np.mod(np.diff(slot, axis=1), k)  # (E, len - 1, M)
    boxes = np.asarray(scenes.furniture_boxes)
    centres = (boxes[..., :2] + boxes[..., 2:]) / 2  # (E, F, 2) (cy, cx)
    half = config.map_size / 2
    angle = np.mod(np.arctan2(centres[..., 1] - half, -(centres[..., 0] - half)), 2 * np.pi)
    for env in range(scenes.num_envs):
        if not {0, 1, 2} <= set(steps[env].ravel().tolist()):
            continue
        spread = True
        for m, category in enumerate(config.categories):
            if category.ordering not in ("clockwise", "counter_clockwise"):
                continue
            order = np.asarray(scenes.visit_order[env, m, : int(scenes.num_slots[env, m])])
            gaps = np.diff(np.sort(angle[env, order]), append=np.sort(angle[env, order])[0]
                           + 2 * np.pi)
            spread &= bool(gaps.min() >= np.deg2rad(50))
        if spread:
            return env
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parents[1] / "docs" / "figures")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    config = FlowSimConfig()
    scenes = generate(jax.random.key(SEED), NUM_CANDIDATES, config)
    env = pick_environment(scenes, config)

    def save(fig, name: str) -> None:
        path = args.out / name
        fig.savefig(path, dpi=DPI, metadata=PNG_METADATA)
        print(f"wrote {path}")

    save(render.draw_scene(scenes, env, 0, config,
                           title=f"A FlowSim environment at τ = 0 (seed {SEED}, env {env})"),
         "flowsim_scene.png")
    save(render.draw_timeline(scenes, env, TIMELINE, config), "flowsim_timeline.png")
    save(render.draw_visit_orders(scenes, env, config), "flowsim_orders.png")

    obj, tau = POSTERIOR_OBJECT, POSTERIOR_TAU
    probs = exact_posterior(scenes.num_slots[env, obj], scenes.slot[env, tau, obj],
                            POSTERIOR_HORIZON, config)
    fig = render.draw_posterior(scenes, env, obj, tau, np.asarray(probs), config)
    fig.axes[0].set_title(f"exact posterior of the {config.categories[obj].name} at "
                          f"τ = {tau + POSTERIOR_HORIZON}, given the map at τ = {tau}",
                          fontsize=10)
    save(fig, "flowsim_posterior.png")
    print(f"wrote {quickstart_figure(args.out)}")


if __name__ == "__main__":
    main()
