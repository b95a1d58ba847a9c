"""Flow-matching maths that knows no model: noise X_0 ~ N(0, I_d) at t = 0, data X_1 at t = 1,
X_t = t·X_1 + (1 − t)·X_0 with target velocity X_1 − X_0; t-samplers, ODE solvers over any
``velocity_fn(x (..., d), t scalar)``, exact log-likelihood.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.validation import check_choice, check_int

T_SAMPLERS = ("uniform", "beta", "logit_normal")
SOLVERS = ("midpoint", "euler", "accurate")
STIFF_GRID_POWER = 4
"""The ``"accurate"`` grid is t = 1 − (1 − s)^STIFF_GRID_POWER for s uniform in [0, 1]."""
VelocityFn = Callable[[jnp.ndarray, jnp.ndarray], jnp.ndarray]


def linear_path(x0: jnp.ndarray, x1: jnp.ndarray, t: jnp.ndarray) -> jnp.ndarray:
    """X_t = t·x1 + (1 − t)·x0. x0, x1 (..., 4); t (...) (one time per box) → (..., 4)."""
    t = jnp.asarray(t)[..., None]
    return t * x1 + (1.0 - t) * x0


def target_velocity(x0: jnp.ndarray, x1: jnp.ndarray) -> jnp.ndarray:
    """Conditional velocity of the linear path, x1 − x0 (independent of t). (..., 4)."""
    return x1 - x0


def sample_t(key: jax.Array, shape: tuple[int, ...], kind: str = "beta") -> jnp.ndarray:
    """Flow times in [0, 1] of the given shape.

    kind: ``"uniform"`` U[0, 1]; ``"beta"`` the reference's t = 0.999·(1 − u), u ~ Beta(1.5, 1)
    (more mass near t = 0, i.e. near the noise); ``"logit_normal"`` t = sigmoid(z), z ~ N(0, 1).
    """
    if kind == "uniform":
        return jax.random.uniform(key, shape)
    if kind == "beta":
        return 0.999 * (1.0 - jax.random.beta(key, 1.5, 1.0, shape))
    if kind == "logit_normal":
        return jax.nn.sigmoid(jax.random.normal(key, shape))
    raise ValueError(f"t_sampler (kind) must be one of {T_SAMPLERS}; got {kind!r}")


def check_solver_args(num_steps: int, method: str) -> tuple[int, str]:
    """A solver's arguments, as ``(num_steps, method)``: ``method`` one of :data:`SOLVERS`, then
    ``num_steps`` grid points, an int >= 2 (>= 3 for ``"accurate"``). The one check of every
    entry point that takes a solver."""
    method = check_choice("method", method, SOLVERS)
    num_steps = check_int("num_steps", num_steps, 3 if method == "accurate" else 2)
    return num_steps, method


def time_grid(num_steps: int, method: str = "midpoint") -> np.ndarray:
    """The ``num_steps`` grid points in [0, 1] (float64, increasing): uniform, or for
    ``"accurate"`` t = 1 − (1 − s)^4, s uniform (docs/design.md, "The likelihood")."""
    if method != "accurate":
        return np.linspace(0.0, 1.0, num_steps)
    return 1.0 - (1.0 - np.linspace(0.0, 1.0, num_steps)) ** STIFF_GRID_POWER


def _odeint(fn, state, t_start: float, t_end: float, num_steps: int, method: str):
    """Integrate d state/dt = fn(state, t) (pytrees) over :func:`time_grid` mapped onto
    [t_start, t_end] (visited backwards when t_start > t_end). ``"accurate"`` steps with RK4.
    The public solvers' ``num_steps`` and ``method`` are checked here."""
    num_steps, method = check_solver_args(num_steps, method)
    lo, hi = min(t_start, t_end), max(t_start, t_end)
    grid = lo + (hi - lo) * time_grid(num_steps, method)
    if t_start > t_end:  # the same points, visited from t_start down to t_end
        grid = grid[::-1]
    add = lambda a, b, h: jax.tree_util.tree_map(lambda x, y: x + h * y, a, b)  # noqa: E731
    combine = lambda k1, k2, k3, k4: jax.tree_util.tree_map(  # noqa: E731
        lambda a, b, c, d: (a + 2.0 * b + 2.0 * c + d) / 6.0, k1, k2, k3, k4)

    def step(carry, interval):
        t, t_next = interval[0], interval[1]
        h = t_next - t
        slope = fn(carry, t)
        if method == "midpoint":
            slope = fn(add(carry, slope, h / 2), t + h / 2)
        elif method == "accurate":
            k2 = fn(add(carry, slope, h / 2), t + h / 2)
            k3 = fn(add(carry, k2, h / 2), t + h / 2)
            k4 = fn(add(carry, k3, h), t_next)
            slope = combine(slope, k2, k3, k4)
        return add(carry, slope, h), None

    intervals = jnp.asarray(np.stack([grid[:-1], grid[1:]], axis=-1), jnp.float32)
    final, _ = jax.lax.scan(step, state, intervals)
    return final


def integrate(velocity_fn: VelocityFn, x0: jnp.ndarray, num_steps: int = 10,
              method: str = "midpoint", t0: float = 0.0, t1: float = 1.0) -> jnp.ndarray:
    """Solve dx/dt = velocity_fn(x, t) from t0 to t1 over ``num_steps`` **grid points** (both ends
    included) with a fixed-step solver; x0 (..., 4) → x at t1.
    """
    return _odeint(velocity_fn, x0, t0, t1, num_steps, method)


def divergence(velocity_fn: VelocityFn, x: jnp.ndarray, t: jnp.ndarray):
    """Exact divergence of the field at every row: returns ``(v, div)`` with v (..., 4), div (...).

    Assumes each row's velocity depends only on that row (true for FlowMaps): one linearisation
    plus 4 JVPs give the exact trace.
    """
    dim = x.shape[-1]
    v, jvp = jax.linearize(lambda y: velocity_fn(y, t), x)
    eye = jnp.eye(dim, dtype=x.dtype).reshape(dim, *([1] * (x.ndim - 1)), dim)
    columns = jax.vmap(jvp)(jnp.broadcast_to(eye, (dim, *x.shape)))  # (dim, ..., dim): J e_i

    div = jnp.einsum("i...i->...", columns)
    return v, div


def standard_normal_log_prob(x: jnp.ndarray) -> jnp.ndarray:
    """log N(x; 0, I) summed over the last axis. (..., d) → (...)."""
    return -0.5 * jnp.sum(jnp.square(x), axis=-1) - 0.5 * x.shape[-1] * math.log(2 * math.pi)


def _augmented(velocity_fn: VelocityFn, sign: float):
    """The change-of-variables system (x, ℓ): dx/dt = v(x, t), dℓ/dt = sign · div v(x, t)."""
    def field(state, t):
        v, div = divergence(velocity_fn, state[0], t)
        return v, sign * div
    return field


def log_prob(velocity_fn: VelocityFn, x1: jnp.ndarray, num_steps: int = 10,
             method: str = "midpoint") -> jnp.ndarray:
    """Exact log-density of x1 under the flow (instantaneous change of variables).

    The augmented ODE (x, ℓ), dℓ/dt = div v, backwards from t = 1 to 0: log p_1(x1) =
    log N(x0; 0, I) − ∫_0^1 div v dt. x1 (..., d) → (...).
    """
    state = (x1, jnp.zeros(x1.shape[:-1], x1.dtype))
    x0, delta = _odeint(_augmented(velocity_fn, 1.0), state, 1.0, 0.0, num_steps, method)
    return standard_normal_log_prob(x0) + delta


def sample_with_log_prob(velocity_fn: VelocityFn, x0: jnp.ndarray, num_steps: int = 10,
                         method: str = "midpoint") -> tuple[jnp.ndarray, jnp.ndarray]:
    """Samples and their exact log-density in one forward solve: x0 (..., d) → (x1, log p (...)).

    The augmented ODE of :func:`log_prob` run forwards; the samples equal :func:`integrate`'s.
    """
    state = (x0, standard_normal_log_prob(x0))
    return _odeint(_augmented(velocity_fn, -1.0), state, 0.0, 1.0, num_steps, method)
