"""A world is one plug-in (issue 55): a toy fourth world, written in this module alone and
registered here, trains, evaluates and searches through the ordinary commands; and nothing
outside the registries compares a world's or a family's name, or probes a world's config."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import re
import typing

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax import evaluate, train, worlds
from flowmaps_jax.flowsim.generate import generate
from flowmaps_jax.flowsim.scenes import make_train_batch
from flowmaps_jax.model.families import MODEL_FAMILIES
from flowmaps_jax.predictor import load_model
from flowmaps_jax.search import cli as search
from flowmaps_jax.tokens import FURNITURE
from flowmaps_jax.training.config import TrainConfig, config_from_dict, smoke_preset
from flowmaps_jax.worlds import flowsim

SRC = pathlib.Path(__file__).resolve().parents[1] / "src" / "flowmaps_jax"


# --------------------------------------------------------------------------- the toy world


class ToyConfig(TrainConfig):
    """The 2-D MLP baseline on a handful of FlowSim maps of the toy world's own seeds."""

    world: typing.ClassVar[str] = "toy"

    def to_dict(self) -> dict:
        return {**super().to_dict(), "world": self.world}

    @classmethod
    def from_dict(cls, data: dict) -> ToyConfig:
        return config_from_dict(cls, {k: v for k, v in data.items() if k != "world"}, "config")


def toy_preset() -> ToyConfig:
    base = dataclasses.replace(smoke_preset(), family="mlp", steps=4, warmup_steps=1,
                               train_envs=8, val_envs=8, val_batches=1, log_every=2,
                               val_every=2, ckpt_every=2, routine_envs=0, preset="toy")
    return ToyConfig(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)})


def toy_splits(cfg, log=print, mesh=None):
    return (generate(jax.random.key(11), cfg.train_envs, cfg.flowsim),
            generate(jax.random.key(12), cfg.val_envs, cfg.flowsim))


def _queries(args):
    """The toy model and 4 draws from its validation maps x 2 queries (tokens, queries,
    targets)."""
    model = load_model(args.checkpoint, args.which)
    scenes = generate(jax.random.key(12), toy_preset().val_envs, model.flowsim)  # toy_splits'
    batch = make_train_batch(jax.random.key(args.seed), scenes, 4, 2, model.flowsim)
    return model, batch


def _write(args, name: str, results: dict) -> int:
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / name).write_text(json.dumps(results))
    return 0


def toy_evaluate(parser, args, argv, stored) -> int:
    """The mean log-density of the targets."""
    model, batch = _queries(args)
    log_p = model.log_prob(batch.tokens, batch.queries, batch.target[:, :, None])
    return _write(args, "toy_eval.json", {"log_prob": float(jnp.mean(log_p)),
                                          "world": stored["world"]})


def toy_search(parser, args, argv, stored) -> int:
    """Looks until the table under the target, tables in the model's order."""
    model, batch = _queries(args)
    p = np.asarray(model.table_probabilities(batch.tokens, batch.queries, 16,
                                             jax.random.key(0)))[..., :-1]  # (B, Q, S)
    boxes, kind = np.asarray(batch.tokens.boxes), np.asarray(batch.tokens.kind)
    target = np.asarray(batch.target)[:, :, None, :2]  # (B, Q, 1, 2) centres y, x
    under = np.all(np.abs(target - boxes[:, None, :, :2]) <= boxes[:, None, :, 2:] / 2, -1)
    under &= (kind == FURNITURE)[:, None]
    rank = np.argsort(np.argsort(-p, -1), -1) + 1
    looks = np.where(under.any(-1), np.where(under, rank, p.shape[-1]).min(-1), p.shape[-1])
    return _write(args, "toy_search.json", {"looks": float(looks.mean())})


TOY = dataclasses.replace(
    flowsim.WORLD, name="toy", splits=toy_splits, families=("mlp",), config=ToyConfig,
    presets={"toy": toy_preset}, evaluate=toy_evaluate, search=toy_search,
    options={"evaluate": (), "search": ()})


@pytest.fixture
def toy_world():
    worlds.register(TOY)
    yield TOY
    del worlds.WORLDS[TOY.name]


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_a_fourth_world_in_one_module_trains_evaluates_and_searches(toy_world, tmp_path):
    run = tmp_path / "run"
    assert train.main(["--preset", "toy", "--run-dir", str(run), "--no-progress"]) == 0
    stored = json.loads((run / "config.json").read_text())
    assert stored["world"] == "toy" and stored["model_kind"] == "mlp"
    assert evaluate.main(["--checkpoint", str(run), "--out", str(tmp_path / "e")]) == 0
    assert np.isfinite(json.loads((tmp_path / "e" / "toy_eval.json").read_text())["log_prob"])
    assert search.main(["--checkpoint", str(run), "--out", str(tmp_path / "s")]) == 0
    looks = json.loads((tmp_path / "s" / "toy_search.json").read_text())["looks"]
    assert 1 <= looks <= TrainConfig().flowsim.max_tokens
    # an option the toy world does not read is refused before anything loads
    assert evaluate.main(["--checkpoint", str(run), "--kl-draws", "7"]) == 2


# --------------------------------------------------------------------------- no names outside


def _outside_registries():
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        if not (rel.startswith("worlds/") or rel == "model/families.py"):
            yield rel, path.read_text()


NOT_A_NAME = {("recorded/flowmaps2026.py", "recorded")}
"""Words that are no world's name where they stand: the authors' format marks a field
"recorded" or "derived"."""


def _compared(text: str, names) -> list[tuple[int, str, str]]:
    """(line, name, the match) of every name compared in ``text`` (``==``, ``!=``, ``in (...)``
    outside a ``for`` header) and every attribute probe of a world's config."""
    quoted = "|".join(re.escape(n) for n in names)
    compare = re.compile(rf"""(==|!=)\s*["']({quoted})["']|["']({quoted})["']\s*(==|!=)"""
                         rf"""|\bin\s*[(\[{{][^)\]}}]*["']({quoted})["']""")
    probe = re.compile(r"""(has|get)attr\([^)]*["'](flowsim|homes|data|world)["']""")
    found = []
    for pattern in (compare, probe):
        for m in pattern.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            if not re.search(r"\bfor\b[^:]*\bin\s*[(\[{]", text.splitlines()[line - 1]):
                found.append((line, next(g for g in m.groups()[1:] if g), m.group(0)))
    return found


def test_no_world_or_family_name_is_compared_outside_the_registries():
    names = sorted({*worlds.WORLDS, *worlds.families(), *MODEL_FAMILIES})
    found = [f"{rel}:{line}: {match}" for rel, text in _outside_registries()
             for line, name, match in _compared(text, names) if (rel, name) not in NOT_A_NAME]
    assert found == []


def test_the_grep_finds_what_it_looks_for():
    text = ('if cfg.world == "recorded":\n    x = hasattr(spec, "homes")\n'
            'y = family in ("mlp", "flowmaps")\nfor part in ("homes", "model"):\n')
    assert [line for line, _, _ in _compared(text, ["recorded", "homes", "mlp"])] == [1, 3, 2]
