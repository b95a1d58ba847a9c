"""Model-facing views of FlowSim scenes: normalised boxes (y, x, h, w) / (map_size − 1), tokens,
queries, batches, the train and validation splits (disjoint streams even for one seed) and
``.npz`` I/O."""

from __future__ import annotations

import functools
import io
import json

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax import boxes as box_geometry
from flowmaps_jax import tokens as tok
from flowmaps_jax.atomic_files import write_file
from flowmaps_jax.flowsim.config import DEFAULT_CONFIG, FlowSimConfig
from flowmaps_jax.flowsim.generate import _FIELDS, _FLOAT_FIELDS, Scenes, generate, validate_scenes
from flowmaps_jax.resources import array_bytes, check_request_size
from flowmaps_jax.untrusted_files import parse_json, read_npz
from flowmaps_jax.validation import (
    check_choice,
    check_file,
    check_instance,
    check_int,
    check_int_array,
    check_key,
    check_output_file,
    check_real,
    check_real_array,
    check_seed,
    prefix_errors,
)

FORMAT_VERSION = 2
TRAIN_SEED = 0
VALIDATION_SEED = 1
_TRAIN_TAG, _VALIDATION_TAG = 0, 1


# ------------------------------------------------------------------------------ boxes


def normalise_boxes(boxes_px, config: FlowSimConfig = DEFAULT_CONFIG) -> jnp.ndarray:
    """Pixel boxes (..., 4) (y0, x0, y1, x1) → normalised (y, x, h, w) / (map_size − 1)."""
    boxes_px = check_real_array("boxes_px", boxes_px, (..., 4))
    check_instance("config", config, FlowSimConfig)
    return box_geometry.normalise(jnp.asarray(boxes_px, jnp.float32), config.map_size)


def denormalise_boxes(boxes, config: FlowSimConfig = DEFAULT_CONFIG) -> jnp.ndarray:
    """Inverse of ``normalise_boxes``: (..., 4) → pixels (y0, x0, y1, x1); NaN or inf pass."""
    boxes = check_real_array("boxes", boxes, (..., 4), finite=False)
    check_instance("config", config, FlowSimConfig)
    return box_geometry.denormalise(jnp.asarray(boxes, jnp.float32), config.map_size)


# ------------------------------------------------------------------------------ tokens


def _tokens(scenes: Scenes, env, tau, config: FlowSimConfig, history: int = 1
            ) -> tok.SceneTokens:
    """Unchecked, jit-able body of ``scene_tokens``."""
    f, m, s = config.num_furniture, config.num_objects, config.max_tokens
    n = env.shape[0]
    if history == 1:  # one map: the paper's tokens
        pad = s - f - m
        boxes = jnp.concatenate([
            box_geometry.normalise(scenes.furniture_boxes[env], config.map_size),
            box_geometry.normalise(scenes.object_boxes[env, tau], config.map_size),
            jnp.zeros((n, pad, 4), jnp.float32)], axis=1)
        descriptor = jnp.concatenate([scenes.furniture_kind[env], scenes.object_kind[env],
                                      jnp.zeros((n, pad), jnp.int32)], axis=1)
        kind = jnp.concatenate([jnp.full((f,), tok.FURNITURE), jnp.full((m,), tok.OBJECT),
                                jnp.zeros((pad,))]).astype(jnp.int32)
        return tok.SceneTokens(boxes=boxes, descriptor=descriptor.astype(jnp.int32),
                               kind=jnp.broadcast_to(kind, (n, s)),
                               mask=jnp.broadcast_to(jnp.arange(s) < f + m, (n, s)),
                               tau=tau.astype(jnp.int32))
    pad = s - f - m * history
    lag = jnp.arange(history)  # 0 = the map at τ, a = the map at τ − a
    time = tau[:, None] - lag[None, :]  # (N, H)
    seen = jnp.repeat(time >= 0, m, axis=1)  # (N, H·M): maps before t = 0 do not exist
    objects = scenes.object_boxes[env[:, None], jnp.maximum(time, 0)]  # (N, H, M, 4)
    boxes = jnp.concatenate([
        box_geometry.normalise(scenes.furniture_boxes[env], config.map_size),
        box_geometry.normalise(objects.reshape(n, history * m, 4), config.map_size)
        * seen[..., None],
        jnp.zeros((n, pad, 4), jnp.float32)], axis=1)
    descriptor = jnp.concatenate([scenes.furniture_kind[env],
                                  jnp.tile(scenes.object_kind[env], (1, history)) * seen,
                                  jnp.zeros((n, pad), jnp.int32)], axis=1)
    kind = jnp.concatenate([jnp.full((f,), tok.FURNITURE), jnp.full((m * history,), tok.OBJECT),
                            jnp.zeros((pad,))]).astype(jnp.int32)
    mask = jnp.concatenate([jnp.ones((n, f), bool), seen, jnp.zeros((n, pad), bool)], axis=1)
    age = None
    if history > 1:
        age = jnp.concatenate([jnp.zeros((f,)), jnp.repeat(lag, m), jnp.zeros((pad,))])
        age = jnp.broadcast_to(age.astype(jnp.int32), (n, s))
    return tok.SceneTokens(boxes=boxes, descriptor=descriptor.astype(jnp.int32),
                           kind=jnp.broadcast_to(kind, (n, s)), mask=mask,
                           tau=tau.astype(jnp.int32), age=age)


def check_history(history, config: FlowSimConfig) -> int:
    """``history`` as an int: the maps read (the one at τ and the H − 1 before it) in 1 … T, and
    their F + M·H tokens within ``config.max_tokens``."""
    check_instance("config", config, FlowSimConfig)
    f, m, s = config.num_furniture, config.num_objects, config.max_tokens
    h = check_int("history", history, 1, config.num_timesteps)
    if f + m * h > s:
        raise ValueError(f"history={h} needs {f + m * h} tokens (F={f} + M={m} × {h}) but "
                         f"max_tokens={s}; raise FlowSimConfig.max_tokens")
    return h


def _check_env_rows(scenes: Scenes, env, config: FlowSimConfig):
    """``env`` (N,) checked, with the shapes and dtypes of ``scenes`` and ``config``."""
    check_instance("config", config, FlowSimConfig)
    validate_scenes(scenes, config, values=False)
    return check_int_array("env", env, 0, scenes.num_envs - 1, shape=(None,))


def scene_tokens(scenes: Scenes, env, tau, config: FlowSimConfig = DEFAULT_CONFIG,
                 history: int = 1) -> tok.SceneTokens:
    """SceneTokens (N, S) of environments ``env`` (N,) at times ``tau`` (N,): F furniture, then
    M object tokens at τ, then (``history`` H > 1) the M object tokens of each map at
    τ − 1 … τ − H + 1 (``age``; maps before t = 0 masked), padded to S = ``config.max_tokens``.
    """
    env = _check_env_rows(scenes, env, config)
    tau = check_int_array("tau", tau, 0, config.num_timesteps - 1, shape=env.shape)
    history = check_history(history, config)
    env, tau = jnp.asarray(env, jnp.int32), jnp.asarray(tau, jnp.int32)
    return _tokens_jit(scenes, env, tau, config, history)


_tokens_jit = jax.jit(_tokens, static_argnames=("config", "history"))


def slot_boxes(scenes: Scenes, env, obj, config: FlowSimConfig = DEFAULT_CONFIG) -> jnp.ndarray:
    """(N, F, 4) normalised (y, x, h, w) box object ``obj`` (N,) of environment ``env`` (N,)
    would have at each position k of its visiting order (zeros for k >= num_slots)."""
    env = _check_env_rows(scenes, env, config)
    obj = check_int_array("obj", obj, 0, config.num_objects - 1, shape=env.shape)
    return _slot_boxes(scenes, jnp.asarray(env, jnp.int32), jnp.asarray(obj, jnp.int32), config)


@functools.partial(jax.jit, static_argnames=("config",))
def _slot_boxes(scenes: Scenes, env, obj, config: FlowSimConfig):
    order = scenes.visit_order[env, obj]  # (N, F)
    furniture = scenes.furniture_boxes[env]  # (N, F, 4)
    table = jnp.take_along_axis(furniture, jnp.maximum(order, 0)[..., None], axis=1)
    half = 0.5 * scenes.object_size[env, obj][:, None, None]
    boxes = box_geometry.normalise(
        box_geometry.centred_squares(box_geometry.corner_centres(table), half), config.map_size)
    valid = jnp.arange(config.num_furniture)[None, :] < scenes.num_slots[env, obj][:, None]
    return jnp.where(valid[..., None], boxes, 0.0)


# ------------------------------------------------------------------------------ queries


def draw_query_times(key, shape_tau, shape_q, config: FlowSimConfig, short_frac: float = 0.0,
                     short_max: int = 3, horizon=None):
    """The paper's query times (unvalidated, traceable): τ uniform in 0..T−2 (``shape_tau``),
    τ_q uniform in τ+1..T−1 (``shape_q``, shape_tau a prefix), or with probability
    ``short_frac`` min(τ + U{1..short_max}, T − 1). With ``horizon`` (int or ``shape_tau``
    ints): τ uniform in 0..T−1−Δτ and τ_q = τ + Δτ.
    """
    t = config.num_timesteps
    key_tau, key_q = jax.random.split(key)
    if horizon is not None:
        tau = jax.random.randint(key_tau, shape_tau, 0, t - horizon)
        return tau, tau + horizon
    tau = jax.random.randint(key_tau, shape_tau, 0, t - 1)
    tau_b = tau.reshape(shape_tau + (1,) * (len(shape_q) - len(shape_tau)))
    tau_q = jax.random.randint(key_q, shape_q, tau_b + 1, t)
    if short_frac > 0:
        key_pick, key_d = jax.random.split(jax.random.fold_in(key_q, 1))
        short = jnp.minimum(tau_b + jax.random.randint(key_d, shape_q, 1, short_max + 1), t - 1)
        tau_q = jnp.where(jax.random.uniform(key_pick, shape_q) < short_frac, short, tau_q)
    return tau, tau_q


@functools.partial(jax.jit, static_argnames=("batch_size", "queries_per_scene", "config",
                                             "short_frac", "short_max", "history"))
def _train_batch(key, scenes: Scenes, batch_size: int, queries_per_scene: int,
                 config: FlowSimConfig, short_frac: float = 0.0,
                 short_max: int = 3, history: int = 1) -> tok.TrainBatch:
    b, q = batch_size, queries_per_scene
    key_env, key_time, key_obj = jax.random.split(key, 3)
    env = jax.random.randint(key_env, (b,), 0, scenes.furniture_boxes.shape[0])
    tau, tau_q = draw_query_times(key_time, (b,), (b, q), config, short_frac, short_max)
    obj = jax.random.randint(key_obj, (b, q), 0, config.num_objects)
    env_q = jnp.broadcast_to(env[:, None], (b, q))
    target = box_geometry.normalise(scenes.object_boxes[env_q, tau_q, obj], config.map_size)
    queries = tok.Queries(descriptor=scenes.object_kind[env_q, obj], tau_q=tau_q)
    return tok.TrainBatch(tokens=_tokens(scenes, env, tau, config, history), queries=queries,
                          target=target)


def make_train_batch(key, scenes: Scenes, batch_size: int, queries_per_scene: int,
                     config: FlowSimConfig = DEFAULT_CONFIG, short_frac: float = 0.0,
                     short_max: int = 3, history: int = 1) -> tok.TrainBatch:
    """A TrainBatch of B uniform scenes × Q queries (object uniform, times by
    :func:`draw_query_times`); target (B, Q, 4) the object's normalised box at τ_q.
    """
    key = check_key(key)
    batch_size = check_int("batch_size", batch_size)
    queries_per_scene = check_int("queries_per_scene", queries_per_scene)
    check_instance("config", config, FlowSimConfig)
    validate_scenes(scenes, config, values=False)
    short_frac = check_real("short_frac", short_frac, 0.0, 1.0)
    short_max = check_int("short_max", short_max)
    history = check_history(history, config)
    check_request_size(f"a batch of {batch_size} scenes x {queries_per_scene} queries",
                       array_bytes((batch_size, config.max_tokens, 7))
                       + array_bytes((batch_size, queries_per_scene, 6)))
    return _train_batch(key, scenes, batch_size, queries_per_scene, config,
                        short_frac, short_max, history)


# ------------------------------------------------------------------------------ datasets


def _split_key(seed: int, tag: int) -> jax.Array:
    return jax.random.fold_in(jax.random.key(check_seed("seed", seed)), tag)


def train_split(config: FlowSimConfig = DEFAULT_CONFIG, num_envs: int = 2500,
                seed: int = TRAIN_SEED, *, mesh=None, part: slice | None = None) -> Scenes:
    """The training environments ``generate(fold_in(key(seed), 0), num_envs, config)``."""
    return generate(_split_key(seed, _TRAIN_TAG), num_envs, config, mesh=mesh, part=part)


def validation_split(config: FlowSimConfig = DEFAULT_CONFIG, num_envs: int = 200,
                     seed: int = VALIDATION_SEED, *, mesh=None) -> Scenes:
    """The held-out environments ``generate(fold_in(key(seed), 1), num_envs, config)``."""
    return generate(_split_key(seed, _VALIDATION_TAG), num_envs, config, mesh=mesh)


# ------------------------------------------------------------------------------ .npz I/O

def save_scenes(path, scenes: Scenes, config: FlowSimConfig = DEFAULT_CONFIG) -> None:
    """Write scenes and their config to one ``.npz`` at ``path``, checked first, whole or not
    at all."""
    path = check_output_file("path", path)
    check_instance("config", config, FlowSimConfig)
    validate_scenes(scenes, config)
    arrays = {name: np.asarray(getattr(scenes, name)) for name in _FIELDS}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, format_version=np.int64(FORMAT_VERSION),
                        config_json=np.asarray(json.dumps(config.to_dict())), **arrays)
    write_file(path, buffer.getvalue(), name="path")  # a temporary file, a rename; no link


def load_scenes(path) -> tuple[Scenes, FlowSimConfig]:
    """Read a file written by ``save_scenes`` (untrusted: ``read_npz``, then ``validate_scenes``);
    ValueError naming ``path`` for anything ``save_scenes`` could not have written."""
    with prefix_errors("load_scenes: "):
        path = check_file("path", path)
        contents = read_npz(repr(path), path, allowed=("format_version", "config_json", *_FIELDS),
                            required=("format_version", "config_json",
                                      *(n for n in _FIELDS if n != "habit")))
    with prefix_errors(f"load_scenes: {path!r}: ", also=(TypeError,)):
        version = check_choice("format_version", check_int("format_version", contents[
            "format_version"], None), (1, FORMAT_VERSION))  # 1: before habits (no habit array)
        if version == 1 and "habit" not in contents and "slot" in contents:  # routine only
            contents["habit"] = np.zeros((contents["slot"].shape[0], contents["slot"].shape[2]),
                                         np.int32)
        if "habit" not in contents:
            raise ValueError("it is missing arrays ['habit']")
        with prefix_errors("it has an invalid config: ", also=(TypeError,)):
            config = FlowSimConfig.from_dict(parse_json("config_json",
                                                         str(contents["config_json"])))
        validate_scenes(Scenes(**{name: contents[name] for name in _FIELDS}), config)
    scenes = Scenes(**{name: jnp.asarray(contents[name],
                                         jnp.float32 if name in _FLOAT_FIELDS else jnp.int32)
                       for name in _FIELDS})
    return scenes, config
