"""The trained default models shipped inside the package (issue 8): they load through
``predictor.load_pretrained``, have the cpu preset's shapes, and put samples on tables of the
queried object's kind."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from flowmaps_jax.flowsim.scenes import scene_tokens, slot_boxes, validation_split
from flowmaps_jax.flowsim.worlds import world_of
from flowmaps_jax.predictor import load_pretrained
from flowmaps_jax.store.pretrained import available
from flowmaps_jax.tokens import Queries
from flowmaps_jax.training.config import get_preset

HABIT_WORLDS = ("preferences", "dynamic", "mixed")
SHIPPED = ("flowmaps", "mlp", "mlp-learned", *(f"flowmaps-{w}" for w in HABIT_WORLDS),
           *(f"flowmaps-{w}-h1" for w in HABIT_WORLDS))


def test_every_default_model_is_shipped():
    assert available() == [*SHIPPED, "flowmaps-homes"]


def test_shipped_homes_model_loads_by_name_and_gives_posteriors():
    """pretrained:flowmaps-homes (issue 35) is the homes preset's model; its receptacle weights
    are distributions over each queried object's allowed receptacles."""
    from flowmaps_jax.flowsim.homes import draw_queries, generate_homes
    predictor = load_pretrained("flowmaps-homes")
    assert predictor.family_name == "flowmaps-homes" and predictor.homes is not None
    assert predictor.model == get_preset("homes").model
    config = get_preset("homes").homes
    homes = generate_homes(jax.random.key(5), config, 2)
    queries = draw_queries(jax.random.key(6), homes, config, 3)
    p = np.asarray(predictor.probabilities(homes, queries, config))
    allowed = np.take_along_axis(np.asarray(homes.object_allowed),
                                 np.asarray(queries.object_index)[..., None], axis=1)
    assert p.shape == allowed.shape
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)
    assert np.all(p[~allowed] == 0.0)


@pytest.mark.parametrize("world", HABIT_WORLDS)
def test_one_model_per_habits_world_and_its_one_map_reference(world):
    for name, history in ((f"flowmaps-{world}", 8), (f"flowmaps-{world}-h1", 1)):
        predictor = load_pretrained(name)
        assert world_of(predictor.flowsim) == world, name
        assert predictor.model.history == history, name


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_weights_have_the_cpu_preset_shapes(name):
    predictor = load_pretrained(name)
    cpu = get_preset("cpu")
    assert predictor.family_name == ("mlp" if name.startswith("mlp") else "flowmaps")
    assert predictor.model.dim == cpu.model.dim
    assert predictor.model.encoder_layers == cpu.model.encoder_layers
    leaves = jax.tree_util.tree_leaves(predictor.params)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    assert predictor.source == f"pretrained:{name}"


def test_shipped_flowmaps_is_the_cpu_preset_model():
    """pretrained:flowmaps comes from README block 1 (the cpu preset) as documented."""
    assert load_pretrained("flowmaps").model == get_preset("cpu").model


def test_shipped_flowmaps_puts_samples_on_tables_of_the_queried_kind():
    predictor = load_pretrained("flowmaps")
    config = predictor.flowsim
    scenes = validation_split(config, num_envs=8)
    env = np.arange(8)
    tau = np.full(8, 4)
    tokens = scene_tokens(scenes, env, tau, config)
    queries = Queries(descriptor=np.asarray(scenes.object_kind, np.int32),
                      tau_q=np.full((8, 3), 6, np.int32))
    x = np.asarray(predictor.sample(tokens, queries, 32, jax.random.key(0)))  # (8, 3, 32, 4)
    boxes = np.asarray(slot_boxes(scenes, np.repeat(env, 3), np.tile(np.arange(3), 8), config))
    boxes = boxes.reshape(8, 3, -1, 4)
    real = np.arange(boxes.shape[2]) < np.asarray(scenes.num_slots)[:, :, None]
    dist = np.linalg.norm(x[:, :, :, None] - boxes[:, :, None], axis=-1)  # to its own route's slots
    dist = np.where(real[:, :, None], dist, np.inf).min(-1)
    assert np.mean(dist < 0.05) > 0.8  # on a table of its own kind, where the object would sit


def test_readme_quick_start_runs_and_draws_the_figure(tmp_path, monkeypatch):
    """The README's quick-start block, run as written (from a fresh clone it needs only the
    shipped weights)."""
    import pathlib
    import re

    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = readme.split("## Quick start")[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README quick start", "exec"), {})
    assert (tmp_path / "fork_next.png").stat().st_size > 10_000


def test_quickstart_script_is_the_readme_block():
    """experiments/quickstart.py is the README's quick-start block, line for line."""
    import pathlib
    import re

    root = pathlib.Path(__file__).resolve().parents[1]
    section = (root / "README.md").read_text().split("## Quick start")[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    script = (root / "experiments" / "quickstart.py").read_text()
    assert script.split('"""\n', 1)[1] == code
