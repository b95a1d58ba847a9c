"""Training the homes model on endless fresh homes: ``python -m flowmaps_jax.train --preset homes``.

Every chunk of ``chunk_steps`` steps draws ``chunk_homes`` fresh homes (``generate_homes`` with
the key ``fold_in(fold_in(key(seed), TRAIN_SALT), chunk)``; regime ``"mixed"`` by default, so
one model covers all four regimes); each step draws ``batch_size`` of them, each at one map hour
τ with ``queries_per_home`` queries (objects uniformly; horizons half from ``DEFAULT_HORIZONS``,
half log-uniform in 1 … ``max_horizon``), inside one jitted step (loss, AdamW on a warm-up +
cosine schedule after global-norm clipping, EMA). The validation homes are fixed, from
:data:`VAL_SEED` (never a training key, nor the evaluation's seed), and scored by the EMA
weights' cross-entropy against the receptacle each object stands on at τ_q: the criterion that
tracks the exact posterior, which picks the ``best`` checkpoint.

The run directory (claimed with :func:`flowmaps_jax.store.rundir.claim`) holds ``config.json``,
``metrics.jsonl`` (train records: mean loss, ce, cfm, grad_norm, lr, steps/s; val records:
``val_loss`` = the validation CE, and whether it is the best) and ``checkpoints/`` (the store
layer's ``last/`` and ``best/``). Ctrl-C saves a checkpoint and stops; a non-finite loss stops
without saving the bad state. ``--resume`` is not supported for the homes presets.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import pathlib
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import optax
from tqdm import tqdm

from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.homes.rollout import generate_homes
from flowmaps_jax.homes.model import FAMILY_NAME, HomesModelConfig, homes_loss, init_params
from flowmaps_jax.homes.queries import DEFAULT_HORIZONS, HomesQueries
from flowmaps_jax.homes.tokens import shared_tau_batch
from flowmaps_jax.store import rundir
from flowmaps_jax.store.checkpoint_store import CheckpointSaveError
from flowmaps_jax.training.loop import StopFlag
from flowmaps_jax.training.overrides import apply_overrides
from flowmaps_jax.training.runlog import RunBook
from flowmaps_jax.training.state import TrainState, ema_update, make_optimizer, make_schedule
from flowmaps_jax.validation import check_args
from flowmaps_jax.validation.composite import After, IntBelow, OutputDir
from flowmaps_jax.validation.fields import Instance, Int, PlainName, Real, check_fields

VAL_SEED = 0x40E5_0001
"""The fixed seed of the validation homes (distinct from every training key and from the
evaluation's ``EVAL_SEED``)."""
TRAIN_SALT = 0x7A1E_0002
"""Training homes of chunk k: ``fold_in(fold_in(key(seed), TRAIN_SALT), k)``."""


@dataclasses.dataclass(frozen=True)
class HomesTrainConfig:
    """A homes training run. ``model``: the network's sizes; ``homes``: the homes world (regime
    ``"mixed"``); ``batch_size`` homes per step × ``queries_per_home`` queries; the optimiser
    (``lr``, ``warmup_steps``, ``b1``, ``b2``, ``weight_decay``, ``clip_norm``, ``ema_decay``);
    fresh data (``chunk_homes`` new homes every ``chunk_steps`` steps); horizons
    (``default_horizon_frac`` of the queries from ``DEFAULT_HORIZONS`` up to ``max_horizon``,
    the rest log-uniform in 1 … ``max_horizon``); ``cfm_weight`` of the placement loss;
    validation (``val_homes`` fixed homes, ``val_batches`` batches of ``batch_size`` of them);
    ``seed``; intervals ``log_every``, ``val_every``, ``ckpt_every``; ``keep_last`` recent
    checkpoints; ``preset``."""

    model: HomesModelConfig = dataclasses.field(default_factory=HomesModelConfig)
    homes: HomesConfig = dataclasses.field(default_factory=lambda: HomesConfig(regime="mixed"))
    batch_size: int = 32
    queries_per_home: int = 8
    steps: int = 5000
    lr: float = 1e-3
    warmup_steps: int = 200
    b1: float = 0.9
    b2: float = 0.999
    weight_decay: float = 0.01
    clip_norm: float = 1.0
    ema_decay: float = 0.998
    chunk_homes: int = 256
    chunk_steps: int = 32
    default_horizon_frac: float = 0.5
    max_horizon: int = 168
    cfm_weight: float = 1.0
    val_homes: int = 256
    val_batches: int = 8
    seed: int = 0
    log_every: int = 50
    val_every: int = 250
    ckpt_every: int = 500
    keep_last: int = 2
    preset: str = "homes"

    def __post_init__(self):
        check_fields(self, _RULES, store=False)

    def to_dict(self) -> dict:
        """JSON-able; ``model_kind`` names the family (what the store layer dispatches on)."""
        out = {"model_kind": FAMILY_NAME, "model": self.model.to_dict(),
               "homes": self.homes.to_dict()}
        out.update({f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                    if f.name not in ("model", "homes")})
        return out

    @classmethod
    def from_dict(cls, data: dict) -> HomesTrainConfig:
        data = dict(data)
        if data.pop("model_kind", FAMILY_NAME) != FAMILY_NAME:
            raise ValueError(f"not a {FAMILY_NAME!r} config")
        model = HomesModelConfig.from_dict(data.pop("model", {}))
        homes = HomesConfig.from_dict(data.pop("homes", {}))
        unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"the homes training config has unknown keys {unknown}")
        return cls(model=model, homes=homes, **data)


_RULES = {
    "model": Instance(HomesModelConfig), "homes": Instance(HomesConfig),
    **{name: Int(1, 1 << 30) for name in (
        "batch_size", "queries_per_home", "steps", "chunk_homes", "chunk_steps",
        "val_batches", "log_every", "val_every", "ckpt_every", "keep_last")},
    "max_horizon": After(lambda got: Int(1, got["homes"].num_hours - got["model"].history, why=(
        f"homes.num_hours={got['homes'].num_hours} - model.history={got['model'].history}: "
        "a map hour needs model.history hours before it and max_horizon after it"))),
    "val_homes": After(lambda got: Int(got["val_batches"] * got["batch_size"], 1 << 30)),
    "seed": Int(0, 2**31 - 1), "lr": Real(0.0, low_open=True),
    **{name: Real(0.0, 1.0, high_open=True) for name in ("b1", "b2", "ema_decay")},
    "weight_decay": Real(0.0), "cfm_weight": Real(0.0),
    "clip_norm": Real(0.0, low_open=True), "default_horizon_frac": Real(0.0, 1.0),
    "preset": PlainName(), "warmup_steps": IntBelow("steps"),
}
"""What each field of :class:`HomesTrainConfig` may hold; ``max_horizon`` and ``val_homes``
are bounded by fields checked before them (``After``)."""


def homes_preset() -> HomesTrainConfig:
    """The shipped homes model's recipe: D = 64, 2 encoder layers, 2 weight block pairs, 2
    placement blocks (0.6M parameters); 32 homes × 8 queries per step, 5,000 steps. Measured on
    the 2-core CPU at nice 19: 1.6–2.2 steps/s beside another training run, about 3.5 with the
    machine nearly idle, so about 25 minutes idle (compilation and validation included) and
    about twice that beside another run."""
    return HomesTrainConfig(steps=5000)


def homes_smoke_preset() -> HomesTrainConfig:
    """A tiny model on short homes: trains in seconds (tests)."""
    return HomesTrainConfig(
        model=HomesModelConfig(dim=16, encoder_layers=1, weight_blocks=1, cdit_blocks=1,
                               heads=2, mlp_ratio=2, freq_bands=4, history=24),
        homes=HomesConfig(regime="mixed", num_hours=96), batch_size=4, queries_per_home=2,
        steps=6, warmup_steps=1, chunk_homes=8, chunk_steps=3, max_horizon=24, val_homes=8,
        val_batches=2, log_every=2, val_every=3, ckpt_every=3, preset="homes-smoke")


PRESETS = {"homes": homes_preset, "homes-smoke": homes_smoke_preset}


# --------------------------------------------------------------------------- data


def draw_batch(key, homes, cfg: HomesTrainConfig, index=None):
    """A training batch (B = ``batch_size`` homes × Q queries) from the homes ``homes``: homes
    ``index`` (B,) (default: uniformly drawn), each at one map hour τ. Jittable."""
    b, q, h = cfg.batch_size, cfg.queries_per_home, cfg.model.history
    k_home, k_tau, k_obj, k_mix, k_set, k_log = jax.random.split(key, 6)
    if index is None:
        index = jax.random.randint(k_home, (b,), 0, homes.num_homes)
    homes = jax.tree.map(lambda a: a[index], homes)
    top = cfg.homes.num_hours - 1 - cfg.max_horizon
    tau = jax.random.randint(k_tau, (b,), h - 1, top + 1)
    logits = jnp.where(homes.object_valid, 0.0, -jnp.inf)[:, None, :]
    obj = jax.random.categorical(k_obj, jnp.broadcast_to(logits, (b, q, logits.shape[-1])))
    fixed = [d for d in DEFAULT_HORIZONS if d <= cfg.max_horizon] or [1]
    chosen = jnp.asarray(fixed, jnp.int32)[jax.random.randint(k_set, (b, q), 0, len(fixed))]
    spread = jnp.floor(jnp.exp(jax.random.uniform(k_log, (b, q))
                               * math.log(cfg.max_horizon + 1.0))).astype(jnp.int32)
    spread = jnp.clip(spread, 1, cfg.max_horizon)
    dt = jnp.where(jax.random.uniform(k_mix, (b, q)) < cfg.default_horizon_frac, chosen, spread)
    tau = jnp.broadcast_to(tau[:, None], (b, q))
    queries = HomesQueries(object_index=obj.astype(jnp.int32), tau=tau, tau_q=tau + dt)
    return shared_tau_batch(homes, queries, cfg.homes, h)


def train_homes(cfg: HomesTrainConfig, chunk: int):
    """The fresh homes of chunk ``chunk``."""
    key = jax.random.fold_in(jax.random.fold_in(jax.random.key(cfg.seed), TRAIN_SALT), chunk)
    return generate_homes(key, cfg.homes, cfg.chunk_homes)


def validation_batches(cfg: HomesTrainConfig):
    """The fixed validation batches (stacked on a leading axis), from :data:`VAL_SEED`."""
    homes = generate_homes(jax.random.key(VAL_SEED), cfg.homes, cfg.val_homes)
    key = jax.random.fold_in(jax.random.key(VAL_SEED), 1)
    draw = jax.jit(lambda k, h, index: draw_batch(k, h, cfg, index))
    batches = [draw(jax.random.fold_in(key, j), homes,
                    jnp.arange(j * cfg.batch_size, (j + 1) * cfg.batch_size))
               for j in range(cfg.val_batches)]
    return jax.tree.map(lambda *a: jnp.stack(a), *batches)


# --------------------------------------------------------------------------- the jitted step


def init_state(cfg: HomesTrainConfig) -> TrainState:
    """Step 0: fresh params (EMA = params), optimiser state and the two raw PRNG keys. The
    optimiser and schedule are the 2-D recipe's (``training.state.make_optimizer``): they read
    lr, warmup_steps, steps, b1, b2, weight_decay and clip_norm, which this config holds too."""
    param_key, rng, data_key = jax.random.split(jax.random.PRNGKey(cfg.seed), 3)
    params = init_params(param_key, cfg.model, cfg.homes)
    return TrainState(step=jnp.zeros((), jnp.int32), params=params,
                      ema_params=jax.tree.map(jnp.copy, params),
                      opt_state=make_optimizer(cfg).init(params), rng=rng, data_key=data_key)


@functools.lru_cache(maxsize=4)
def make_train_step(cfg: HomesTrainConfig):
    """Jitted ``(state, homes) -> (state, metrics)``: draws step i's batch from ``homes`` with
    ``fold_in(data_key, i)``, its noise with ``fold_in(rng, i)``; ``state`` is donated."""
    tx = make_optimizer(cfg)
    schedule = make_schedule(cfg)

    def step(state: TrainState, homes):
        batch = draw_batch(jax.random.fold_in(state.data_key, state.step), homes, cfg)
        loss_fn = lambda p: homes_loss(p, cfg.model, cfg.homes, batch,  # noqa: E731
                                       jax.random.fold_in(state.rng, state.step), cfg.cfm_weight)
        (_, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = {"loss": aux["loss"], "ce": aux["ce"], "cfm": aux["cfm"],
                   "grad_norm": optax.tree.norm(grads), "lr": schedule(state.step)}
        return state.replace(step=state.step + 1, params=params, opt_state=opt_state,
                             ema_params=ema_update(state.ema_params, params, cfg.ema_decay)
                             ), metrics

    return jax.jit(step, donate_argnums=0)


@functools.lru_cache(maxsize=4)
def make_eval(cfg: HomesTrainConfig):
    """Jitted ``(params, batches) -> (mean CE, mean CFM)`` with fixed noise (comparable across
    steps)."""
    key = jax.random.fold_in(jax.random.key(VAL_SEED), 2)

    def evaluate(params, batches):
        def one(args):
            batch, j = args
            _, aux = homes_loss(params, cfg.model, cfg.homes, batch, jax.random.fold_in(key, j),
                                cfg.cfm_weight)
            return aux["ce"], aux["cfm"]

        ce, cfm = jax.lax.map(one, (batches, jnp.arange(cfg.val_batches)))
        return jnp.mean(ce), jnp.mean(cfm)

    return jax.jit(evaluate)


# --------------------------------------------------------------------------- the loop


@check_args(cfg=Instance(HomesTrainConfig), run_dir=OutputDir())
def run(cfg: HomesTrainConfig, run_dir, *, overwrite: bool = False, progress: bool = True,
        log: Callable[[str], None] = print) -> dict:
    """Train ``cfg`` into ``run_dir`` (see the module docstring). Returns ``{"status": "done" |
    "interrupted" | "nan", "step", "best_step", "best_val_ce", "run_dir"}``."""
    with rundir.claim(run_dir, resume=False, overwrite=overwrite, log=log), StopFlag() as stop:
        rundir.write_atomic(run_dir / "config.json", json.dumps(cfg.to_dict(), indent=2) + "\n")
        log(f"Run directory: {run_dir.absolute()} (config.json, metrics.jsonl, checkpoints/)")
        train_step, evaluate = make_train_step(cfg), make_eval(cfg)
        val = validation_batches(cfg)
        state = init_state(cfg)
        status, val_ce, homes = "done", float("nan"), None
        with RunBook(run_dir, cfg, kept=None, window=None) as book, tqdm(
                total=cfg.steps, unit="step", disable=not progress, dynamic_ncols=True,
                desc="train homes") as bar:
            stop.start_steps()
            for i in range(cfg.steps):
                if i % cfg.chunk_steps == 0:
                    homes = train_homes(cfg, i // cfg.chunk_steps)
                start = time.perf_counter()
                state, metrics = train_step(state, homes)
                metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
                book.add_step(metrics, None if i == 0 else time.perf_counter() - start)
                done = i + 1
                if not math.isfinite(metrics["loss"]):
                    status = "nan"
                    log(f"Non-finite loss at step {done}: stopped without saving that state")
                    break
                if done % cfg.log_every == 0 or done == cfg.steps:
                    book.write_train(done, cfg.batch_size * cfg.queries_per_home)
                if done % cfg.val_every == 0 or done == cfg.steps:
                    val_ce = float(evaluate(state.ema_params, val)[0])
                    book.write_val(state, done, val_ce)
                if done % cfg.ckpt_every == 0 or done == cfg.steps or stop.requested:
                    try:
                        book.save(state)
                    except CheckpointSaveError as err:
                        raise book.save_failed(err, done) from err
                bar.update(1)
                bar.set_postfix(loss=f"{metrics['loss']:.3f}", ce=f"{metrics['ce']:.3f}",
                                val_ce=f"{val_ce:.3f}", refresh=False)
                if stop.requested:
                    status = "interrupted"
                    break
        result = {"status": status, "step": int(state.step) if status != "nan" else done - 1,
                  "best_step": book.best_step, "best_val_ce": book.best_loss,
                  "run_dir": run_dir}
    ckpt = run_dir / "checkpoints"
    log(f"{status}: step {result['step']} of {cfg.steps}; best validation CE "
        f"{result['best_val_ce']} at step {result['best_step']} (the step loaded by default)")
    log(f"Load it:   flowmaps_jax.homes.predictor.HomesPredictor.load({str(ckpt)!r})")
    log(f"Ship it:   python -m flowmaps_jax.export --checkpoint {ckpt} --name flowmaps-homes")
    return result


# --------------------------------------------------------------------------- the command line


def main_from_args(args) -> int:
    """``python -m flowmaps_jax.train --preset homes …`` (parsed by
    :mod:`flowmaps_jax.training.cli`): 0 done, 1 non-finite loss, 130 interrupted.
    ``ValueError`` for arguments the homes presets do not take."""
    for flag, value in (("--resume", args.resume), ("--from-step", args.from_step),
                        ("--family", args.family), ("--init-from", args.init_from),
                        ("--stop-at", args.stop_at)):
        if value not in (None, False):
            raise ValueError(f"{flag} is not supported with --preset {args.preset}")
    cfg = PRESETS[args.preset]()
    cfg = apply_overrides(cfg, args.overrides)
    if args.steps is not None:
        cfg = dataclasses.replace(cfg, steps=args.steps,
                                  warmup_steps=min(cfg.warmup_steps, max(args.steps - 1, 0)))
    run_dir = pathlib.Path(args.run_dir if args.run_dir is not None else
                           pathlib.Path("runs") / f"{cfg.preset}-{time.strftime('%Y%m%d-%H%M%S')}")
    result = run(cfg, run_dir, overwrite=args.overwrite, progress=not args.no_progress)
    return {"nan": 1, "interrupted": 130}.get(result["status"], 0)


__all__ = ["PRESETS", "TRAIN_SALT", "VAL_SEED", "HomesTrainConfig", "draw_batch", "init_state",
           "main_from_args", "make_eval", "make_train_step", "run", "validation_batches"]
