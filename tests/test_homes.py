"""FlowSim homes: the config's refusals, generated homes, the exact posterior (against
Monte-Carlo chains and brute-force enumeration), jit / vmap, and the on-disk format.

Tiny sizes: one "mixed" config (every regime in one compiled program) over 8 days, 6 homes, and
the same with other preference contexts (``day_phases``), for the tests that follow the law."""

from __future__ import annotations

import dataclasses
import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax.flowsim.homes import (
    FIELDS,
    NUM_CONTEXTS,
    REGIMES,
    Homes,
    HomesConfig,
    ObjectClass,
    ReceptacleClass,
    context_of,
    favourite_weights,
    filtered_posterior,
    generate_homes,
    homes_from_keys,
    homes_history_posterior,
    homes_posterior,
    load_homes,
    object_boxes,
    room_adjacency,
    save_homes,
    simulate,
    transition_matrix,
    validate_homes,
)
from flowmaps_jax.flowsim.homes.export import schema_path
from flowmaps_jax.flowsim.homes.floorplan import geodesic_distances
from flowmaps_jax.flowsim.homes.rollout import sample_paths

CONFIG = HomesConfig(regime="mixed", num_hours=192)
RHYTHMS = dataclasses.replace(CONFIG, day_phases=(7, 9, 17, 18))  # 07–09, 09–17, 17–18, 18–07
NUM_HOMES = 6


@pytest.fixture(scope="module")
def homes() -> Homes:
    return generate_homes(jax.random.key(0), CONFIG, NUM_HOMES)


@pytest.fixture(scope="module")
def rhythm_homes() -> Homes:
    return generate_homes(jax.random.key(0), RHYTHMS, NUM_HOMES)


BOTH = pytest.mark.parametrize("config", [CONFIG, RHYTHMS], ids=["six-hour", "rhythms"])
"""Run a test on the default contexts and on ``RHYTHMS``' (its homes: ``_homes_of``)."""


def _homes_of(request, config: HomesConfig) -> Homes:
    return request.getfixturevalue("homes" if config is CONFIG else "rhythm_homes")


def _context(t: int, phases) -> int:
    """c(t) as docs/flowsim.md states it: the phase of the last start <= hour of day (the last
    phase before the first start), + 4 on Saturday and Sunday."""
    started = [i for i, start in enumerate(phases) if start <= t % 24]
    return (started[-1] if started else len(phases) - 1) + 4 * ((t // 24) % 7 >= 5)


def _objects_by_regime(homes: Homes, min_allowed: int = 2, max_allowed: int = 18):
    """{regime: (home index, object index)} of one valid object per regime."""
    regime, valid, num = (np.asarray(a) for a in (homes.regime, homes.object_valid,
                                                  homes.num_allowed))
    found = {}
    for r in range(len(REGIMES)):
        e, m = np.nonzero((regime == r) & valid & (num >= min_allowed) & (num <= max_allowed))
        assert e.size, f"no {REGIMES[r]} object with {min_allowed}..{max_allowed} places"
        found[r] = (int(e[0]), int(m[0]))
    return found


# ---------------------------------------------------------------------------- the config


def test_vocabulary_sizes_and_round_trip():
    config = HomesConfig()
    assert len(config.room_types) >= 5 and len(config.receptacle_classes) >= 12
    assert len(config.object_classes) >= 20 and config.max_objects <= 15
    assert config.num_hours == 4 * 7 * 24
    assert HomesConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    assert len(config.vocabulary) == config.vocabulary_size
    assert context_of(0) == 0 and context_of(13) == 2 and context_of(5 * 24 + 19) == 7


def test_day_phases_default_is_the_six_hour_contexts_and_others_follow_the_docs():
    week = np.arange(7 * 24)
    before = (week % 24) // 6 + 4 * ((week // 24) % 7 >= 5)  # the contexts before day_phases
    assert HomesConfig().day_phases == (0, 6, 12, 18)
    for t in week:
        assert context_of(int(t)) == before[t] == _context(int(t), (0, 6, 12, 18))
        assert context_of(int(t), RHYTHMS.day_phases) == _context(int(t), RHYTHMS.day_phases)
    np.testing.assert_array_equal(context_of(week), before)
    np.testing.assert_array_equal(context_of(jnp.asarray(week)), before)
    rhythm = context_of(jnp.asarray(week), RHYTHMS.day_phases)
    assert rhythm.dtype == jnp.int32
    # Monday 03, 07, 08, 09, 16, 17, 18, 23 h; Saturday 06 and 08 h
    hours = [3, 7, 8, 9, 16, 17, 18, 23, 5 * 24 + 6, 5 * 24 + 8]
    np.testing.assert_array_equal(rhythm[np.asarray(hours)], [3, 0, 0, 1, 1, 2, 3, 3, 7, 4])
    # a stored config from before the field loads with the default; the field round-trips
    old = {k: v for k, v in HomesConfig().to_dict().items() if k != "day_phases"}
    assert HomesConfig.from_dict(old) == HomesConfig()
    assert HomesConfig.from_dict(json.loads(json.dumps(RHYTHMS.to_dict()))) == RHYTHMS


def _replace_class(field: str, name: str, **changes) -> dict:
    entries = getattr(HomesConfig(), field)
    return {field: tuple(dataclasses.replace(e, **changes) if e.name == name else e
                         for e in entries)}


BAD_CONFIGS = [
    ({"rooms": ("kitchen", "garage")}, "rooms: unknown room type 'garage'"),
    (_replace_class("receptacle_classes", "bed", rooms=("attic",)),
     "receptacle_classes: 'bed' rooms: unknown room type"),
    (_replace_class("object_classes", "mug", receptacles=("cupboard",)),
     "object_classes: 'mug' receptacles: unknown receptacle class"),
    (_replace_class("object_classes", "mug", receptacles=()), "object_classes: 'mug' receptacles"),
    ({"rooms": ("kitchen", "kitchen", "kitchen", "kitchen", "kitchen", "kitchen")},
     "object_classes: 'remote' may stand on no receptacle class"),
    (_replace_class("receptacle_classes", "bed", size=(1.6, -2.0, 0.5)),
     "receptacle_classes: 'bed' size"),
    (_replace_class("object_classes", "book", size=(0.1, 0.2, 0.0)), "object_classes: 'book' size"),
    ({"max_tokens": 30}, "max_tokens"),
    ({"max_vocabulary": 40}, "max_vocabulary"),
    ({"objects_per_home": (10, 16)}, "objects_per_home"),
    ({"num_hours": 1}, "num_hours"),
    ({"regime": "chaotic"}, "regime"),
    ({"home_width": (3.0, 4.0)}, "home_width"),
    ({"activity": (1.0,) * 23}, "activity"),
    ({"receptacles_per_room": (2, 5)}, "receptacles_per_room"),
    ({"grid_rows": 4}, "rooms"),
    ({"preference_mass": 1.5}, "preference_mass"),
    ({"day_phases": (0, 6, 12)}, "day_phases must be a tuple of 4 start hours"),
    ({"day_phases": (0, 6, 12, 24)}, r"day_phases\[3\] must be an int in 0..23"),
    ({"day_phases": (-1, 6, 12, 18)}, r"day_phases\[0\] must be an int in 0..23"),
    ({"day_phases": (0, 6.5, 12, 18)}, r"day_phases\[1\] must be an int"),
    ({"day_phases": (7, 9, 9, 18)}, "day_phases must be strictly increasing"),
    ({"day_phases": (18, 7, 9, 17)}, "day_phases must be strictly increasing"),
    ({"day_phases": "7,9,17,18"}, "day_phases must be a tuple"),
]


@pytest.mark.parametrize(("changes", "message"), BAD_CONFIGS)
def test_bad_config_names_the_field(changes, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        HomesConfig(**changes)


def test_bad_generate_arguments():
    with pytest.raises(ValueError, match="num_homes"):
        generate_homes(jax.random.key(0), CONFIG, 0)
    with pytest.raises(ValueError, match="config"):
        generate_homes(jax.random.key(0), {"regime": "mixed"}, 2)
    with pytest.raises(ValueError, match="key"):
        generate_homes(3, CONFIG, 2)


# ---------------------------------------------------------------------------- homes


def test_shapes_determinism_and_validity(homes):
    validate_homes(homes, CONFIG)
    r, m, t = CONFIG.max_receptacles, CONFIG.max_objects, CONFIG.num_hours
    assert homes.receptacle.shape == (NUM_HOMES, t, m)
    assert homes.receptacle_box.shape == (NUM_HOMES, r, 6)
    assert homes.favourite.shape == (NUM_HOMES, m, NUM_CONTEXTS)
    for name, (_, dtype, _, _) in FIELDS.items():
        assert getattr(homes, name).dtype == np.dtype(dtype), name
    again = generate_homes(jax.random.key(0), CONFIG, NUM_HOMES)
    other = generate_homes(jax.random.key(1), CONFIG, NUM_HOMES)
    for a, b in zip(jax.tree.leaves(homes), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(homes.receptacle, other.receptacle)
    assert set(np.unique(homes.regime[homes.object_valid])) == set(range(len(REGIMES)))
    for field in ("favourite", "receptacle", "cycle"):  # an index past R: named, no IndexError
        wrong = np.asarray(getattr(homes, field)).copy()
        wrong.flat[0] = CONFIG.max_receptacles
        with pytest.raises(ValueError, match=f"homes.{field} must lie"):
            validate_homes(dataclasses.replace(homes, **{field: wrong}), CONFIG)


def test_small_requests_share_one_program_and_are_their_own_homes(homes):
    """Fewer than SMALL_REQUEST homes are computed as that many and cut back: one compiled
    program for every small number, and the homes are the request's own, bit for bit."""
    compiled = homes_from_keys._cache_size()
    for n in (1, 2):
        for a, b in zip(jax.tree.leaves(generate_homes(jax.random.key(0), CONFIG, n)),
                        jax.tree.leaves(homes), strict=True):
            np.testing.assert_array_equal(a, np.asarray(b)[:n])
    assert homes_from_keys._cache_size() - compiled <= 1


def test_rooms_receptacles_and_doors(homes):
    config = CONFIG
    for e in range(NUM_HOMES):
        home = jax.tree.map(np.asarray, homes.home(e))
        assert sorted(home.room_type) == sorted(config.room_type_index)
        valid = home.receptacle_valid
        room = home.room_box[home.receptacle_room]
        box = home.receptacle_box
        lo, hi = box[:, :2] - box[:, 3:5] / 2, box[:, :2] + box[:, 3:5] / 2
        assert np.all((lo >= room[:, :2] - 1e-5) & (hi <= room[:, 2:] + 1e-5) | ~valid[:, None])
        assert np.all(box[valid, 3:] > 0)
        allows = np.asarray(config.room_allows())
        cls = home.receptacle_class
        assert np.all(allows[home.room_type[home.receptacle_room[valid]], cls[valid]])
        count = valid.reshape(config.num_rooms, -1).sum(1)
        assert np.all((count >= 2) & (count <= 3))
        objects = np.asarray(config.object_allows())
        for i in np.nonzero(home.object_valid)[0]:  # allowed == the classes it may stand on
            expect = valid & objects[home.object_class[i], np.maximum(cls, 0)]
            np.testing.assert_array_equal(home.object_allowed[i], expect)
        adjacency = np.asarray(room_adjacency(home.door_rooms, home.door_valid,
                                              config.num_rooms))
        reach = np.eye(config.num_rooms, dtype=bool)
        for _ in range(config.num_rooms):
            reach = reach | (reach.astype(int) @ adjacency.astype(int) > 0)
        assert reach.all(), "every home is connected"
        for (a, b), pos, ok in zip(home.door_rooms, home.door_position, home.door_valid,
                                   strict=True):
            if ok:  # on the boundary of both rooms
                for k in (a, b):
                    x0, y0, x1, y1 = home.room_box[k]
                    on_x = np.isclose(pos[0], x0) | np.isclose(pos[0], x1)
                    on_y = np.isclose(pos[1], y0) | np.isclose(pos[1], y1)
                    assert (on_x or on_y) and x0 - 1e-5 <= pos[0] <= x1 + 1e-5


def test_object_boxes_stand_on_their_receptacles(homes):
    boxes = np.asarray(object_boxes(homes, 30, CONFIG))
    valid = np.asarray(homes.object_valid)
    under = np.take_along_axis(np.asarray(homes.receptacle_box),
                               np.maximum(np.asarray(homes.receptacle[:, 30]), 0)[..., None],
                               axis=1)
    np.testing.assert_allclose(boxes[valid][:, :2], under[valid][:, :2])
    np.testing.assert_allclose(boxes[valid][:, 2] - boxes[valid][:, 5] / 2, under[valid][:, 5],
                               atol=1e-6)
    assert np.all(boxes[~valid] == 0) and np.all(boxes[valid][:, 3:] > 0)


def test_geodesics(homes):
    for e in range(NUM_HOMES):
        home = jax.tree.map(np.asarray, homes.home(e))
        v = home.receptacle_valid
        d = home.receptacle_distance[np.ix_(v, v)]
        xy = home.receptacle_box[v, :2]
        straight = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
        same = home.receptacle_room[v][:, None] == home.receptacle_room[v][None]
        assert np.all(np.isfinite(d)) and np.allclose(d, d.T, atol=1e-4)
        assert np.all(d >= straight - 1e-4)
        np.testing.assert_allclose(d[same], straight[same], atol=1e-4)
        assert np.all(d[:, :, None] <= d[:, None, :] + d.T[None, :, :] + 1e-3)  # triangle
    # two rooms side by side, one door at (2, 1): around through the door
    dist = geodesic_distances(jnp.asarray([[1.0, 3.0], [3.0, 3.0]]), jnp.asarray([0, 1]),
                              jnp.asarray([True, True]), jnp.asarray([[2.0, 1.0]]),
                              jnp.asarray([[0, 1]]), jnp.asarray([True]), 2)
    np.testing.assert_allclose(dist[0, 1], 2 * np.sqrt(5.0), rtol=1e-6)


def test_objects_without_a_receptacle_are_masked():
    classes = {c.name: c for c in HomesConfig().object_classes}
    config = HomesConfig(rooms=("kitchen", "bathroom"), grid_rows=1, receptacles_per_room=(1, 1),
                         objects_per_home=(3, 3), num_hours=24, max_tokens=8,
                         object_classes=(classes["soap"], classes["knife"],
                                         classes["toothbrush"]))
    homes = generate_homes(jax.random.key(2), config, 32)
    validate_homes(homes, config)
    valid = np.asarray(homes.object_valid)
    assert 0 < valid.sum() < valid.size
    assert np.all(np.asarray(homes.receptacle)[~np.broadcast_to(valid[:, None], (32, 24, 3))]
                  == -1)
    assert not np.asarray(homes.object_allowed)[~valid].any()
    e, m = (int(i[0]) for i in np.nonzero(~valid))
    with pytest.raises(ValueError, match=r"object_index .* masked"):
        homes_posterior(homes.home(e), m, 0, 5, config)


# ---------------------------------------------------------------------------- the posterior


def _matrices(home: Homes, m: int, hours) -> np.ndarray:
    return np.stack([np.asarray(transition_matrix(home, m, t, CONFIG), np.float64)
                     for t in hours])


def test_transition_matrices_are_stochastic_on_allowed(homes):
    for r, (e, m) in _objects_by_regime(homes).items():
        home = homes.home(e)
        allowed = np.asarray(home.object_allowed[m])
        for t in (0, 7, 30, 130):
            p = np.asarray(transition_matrix(home, m, t, CONFIG))
            np.testing.assert_allclose(p[allowed].sum(1), 1.0, atol=1e-6)
            assert np.all(p[~allowed] == 0) and np.all(p[:, ~allowed] == 0) and p.min() >= 0
        if REGIMES[r] == "balanced":  # doubly stochastic: occupancy stays uniform
            np.testing.assert_allclose(p[np.ix_(allowed, allowed)].sum(0), 1.0, atol=1e-6)


def test_posterior_matches_enumeration_of_all_paths(homes):
    tau, tau_q = 20, 24  # crosses 23:00 -> 00:00 (activity) and a context change
    for r, (e, m) in _objects_by_regime(homes, max_allowed=6).items():
        home = homes.home(e)
        mats = _matrices(home, m, range(tau, tau_q))
        allowed = np.flatnonzero(np.asarray(home.object_allowed[m]))
        start = int(home.receptacle[tau, m])
        brute = np.zeros(CONFIG.max_receptacles)
        for path in itertools.product(allowed, repeat=tau_q - tau):
            states = (start, *path)
            brute[path[-1]] += np.prod([mats[i, states[i], states[i + 1]]
                                        for i in range(tau_q - tau)])
        p = np.asarray(homes_posterior(home, m, tau, tau_q, CONFIG))
        np.testing.assert_allclose(p, brute, atol=1e-6, err_msg=REGIMES[r])


@BOTH
def test_posterior_matches_monte_carlo(request, config):
    """The generator's sampler follows the law the posterior computes (16 h -> 07 h next day:
    every context boundary of both configs)."""
    homes = _homes_of(request, config)
    chains, tau, tau_q = 20_000, 40, 55
    for r, (e, m) in _objects_by_regime(homes, min_allowed=3).items():
        home = homes.home(e)
        p = np.asarray(homes_posterior(home, m, tau, tau_q, config), np.float64)
        allowed = np.asarray(home.object_allowed[m])
        np.testing.assert_allclose(p.sum(), 1.0, atol=1e-5)
        assert np.all(p[~allowed] == 0)
        draws = np.asarray(simulate(jax.random.key(r), home, m, tau, tau_q, chains, config))
        assert np.all(allowed[draws])
        freq = np.bincount(draws, minlength=p.size) / chains
        se = np.sqrt(np.maximum(p * (1 - p), 1e-12) / chains)
        assert np.all(np.abs(freq - p) <= 3 * se + 1e-4), (REGIMES[r], freq, p)


def _doc_law(home, m, config: HomesConfig):
    """One object's law written from docs/flowsim.md alone, over its cycle positions 0 … n − 1:
    (favourite assignments (A, C): all n^C for preferences, one dummy row otherwise;
    step(t, k) -> P_t (n, n) when context c(t)'s favourite is cycle position k; the cycle)."""
    n = int(home.num_allowed[m])
    cycle = np.asarray(home.cycle[m])[:n]
    regime = REGIMES[int(home.regime[m])]
    rho = {"preferences": config.preference_move, "balanced": config.balanced_move,
           "frequent": config.frequent_move, "routine": 1.0}[regime]
    move = rho * np.asarray(config.activity, np.float64)
    eye, shift = np.eye(n), np.roll(np.eye(n), 1, axis=1)  # shift: position i -> i + 1
    if regime == "routine":  # m = 1 at every hour
        p0, p1, p2 = config.routine_probs
        move, kernel = np.ones(24), p0 * eye + p1 * shift + p2 * shift @ shift
    elif regime == "balanced":  # next on the cycle, else any other place
        c = config.balanced_cycle
        kernel = c * shift + (1 - c) * (1 - eye) / (n - 1)
    elif regime == "frequent":
        g = np.asarray(home.receptacle_distance, np.float64)[np.ix_(cycle, cycle)]
        w = np.where(eye > 0, 0.0, np.exp(-g / config.frequent_length))
        kernel = w / w.sum(1, keepdims=True)
    else:
        mass = config.preference_mass

        def step(t, k):
            pi = np.where(np.arange(n) == k, mass, (1 - mass) / (n - 1))
            return (1 - move[t % 24]) * eye + move[t % 24] * np.ones((n, 1)) * pi[None, :]
        return np.asarray(list(itertools.product(range(n), repeat=NUM_CONTEXTS))), step, cycle
    return (np.zeros((1, NUM_CONTEXTS), int),
            lambda t, k: (1 - move[t % 24]) * eye + move[t % 24] * kernel, cycle)


def _enumerated_posteriors(home, m, tau, tau_q, config: HomesConfig, from_hour_0: bool = True,
                           seen=None, first=None):
    """(τ + 1, n) float64: row a is P(s_{τ_q} = cycle position j | s_a … s_τ), by brute force
    over the whole generative process: every favourite assignment (uniform), the uniform start
    at hour 0 and every path, as one forward pass over the joint (assignment, state) that
    multiplies in each observation of the window. ``from_hour_0=False`` starts the joint at
    hour a instead (the window's transitions only: the formula issue 46 found wrong). With
    ``seen`` ((τ + 1,) bool), the law is known (the home's own favourites only) and only the
    hours ``seen`` marks are observed (row 0: the known-parameters filter's posterior). With
    ``first`` (ints), only those rows a, in that order."""
    favs, step, cycle = _doc_law(home, m, config)
    n = cycle.size
    where = {int(rec): i for i, rec in enumerate(cycle)}
    s = [where[int(x)] for x in np.asarray(home.receptacle[:tau + 1, m])]
    if seen is not None and len(favs) > 1:
        mine = [where.get(int(f), -1) for f in np.asarray(home.favourite[m])]
        favs = favs[np.all(favs == mine, axis=1)]
    seen = np.ones(tau + 1, bool) if seen is None else seen
    # the window's first hour a (history τ + 1 − a); each row is its own forward pass
    first = np.arange(tau + 1) if first is None else np.asarray(first)
    p = np.full((first.size, len(favs), n), 1.0 / (len(favs) * n))
    for t in range(tau_q):
        if t <= tau and seen[t]:
            p[first <= t] *= np.eye(n)[s[t]]
            if not from_hour_0:  # forget what came before a: the start at a is uniform
                p[first == t] = np.eye(n)[s[t]] / len(favs)
        for k in range(n):  # assignments whose favourite of context c(t) is k share P_t
            chosen = favs[:, _context(t, config.day_phases)] == k
            if chosen.any():
                p[:, chosen] = p[:, chosen] @ step(t, k)
    post = p.sum(1)
    return post / post.sum(1, keepdims=True), cycle


@BOTH
def test_history_posterior_matches_enumeration_of_the_whole_process(request, config):
    """Every regime, n = 2 and 3 places, every history H = 1 … τ + 1 (H = τ + 1: from hour 0);
    and the known-parameters filter on a random half of the hours."""
    homes = _homes_of(request, config)
    rng = np.random.default_rng(54)
    regime, valid, num = (np.asarray(a) for a in (homes.regime, homes.object_valid,
                                                  homes.num_allowed))
    differs = 0.0
    for r, n in itertools.product(range(len(REGIMES)), (2, 3)):
        e, m = (int(i[0]) for i in np.nonzero((regime == r) & valid & (num == n)))
        home = homes.home(e)
        # 131 = Friday 11:00, so the window's contexts include the weekend's after τ
        for tau, tau_q in ((40, 47), (131, 155)) if n == 2 else ((40, 47),):
            want, cycle = _enumerated_posteriors(home, m, tau, tau_q, config)
            got = jax.vmap(lambda h, home=home, m=m, tau=tau, tau_q=tau_q: homes_history_posterior(
                home, m, tau, tau_q, h, config))(jnp.arange(tau + 1, 0, -1))  # a = 0 … τ
            got = np.asarray(got, np.float64)
            np.testing.assert_allclose(got[:, cycle], want, atol=1e-6, err_msg=REGIMES[r])
            np.testing.assert_allclose(got.sum(-1), 1.0, atol=1e-6)
            observed = np.zeros((config.num_hours, config.max_objects), bool)
            observed[:tau + 1, m] = seen = rng.random(tau + 1) < 0.5
            known, _ = _enumerated_posteriors(home, m, tau, tau_q, config, seen=seen)
            filtered = np.asarray(filtered_posterior(home, m, observed, tau, tau_q, config))
            np.testing.assert_allclose(filtered[cycle], known[0], atol=1e-6, err_msg=REGIMES[r])
            if REGIMES[r] == "preferences":  # the test can fail: the window alone is wrong
                window_only, _ = _enumerated_posteriors(home, m, tau, tau_q, config, False)
                differs = max(differs, np.abs(window_only - want).max())
                weights = np.asarray(jax.jit(favourite_weights, static_argnums=(3, 4))(
                    home, m, tau, 5, config))  # one compiled program, not one per operation
                np.testing.assert_allclose(weights.sum(-1), 1.0, atol=1e-6)
            else:  # Markov: the history changes nothing
                np.testing.assert_allclose(got, np.broadcast_to(
                    homes_posterior(home, m, tau, tau_q, config), got.shape), atol=1e-6)
    assert differs > 0.05, "p(s_a | f) matters on these queries"


def _redrawn_paths(key, home, m, hours: int, num: int, config: HomesConfig):
    """(num, hours) receptacles at hours 0 … hours − 1 of object m of ``home`` (a preferences
    object), by the generator's own sampler (``rollout.sample_paths``), each path with its own
    favourites (uniform over the allowed places, per context) and uniform start at hour 0."""
    fields = {name: value[m:m + 1] for name, value in home.as_dict().items()
              if name in ("regime", "cycle", "num_allowed", "object_allowed", "object_valid",
                          "favourite")}
    fields["receptacle_distance"] = home.receptacle_distance
    n = fields["num_allowed"]
    alone = dataclasses.replace(config, regime="preferences")

    def path(k):
        k_fav, k_start, k_path = jax.random.split(k, 3)
        pick = lambda u: jnp.minimum(jnp.floor(u * n).astype(jnp.int32), n - 1)  # noqa: E731
        favourite = jnp.take(fields["cycle"][0], pick(jax.random.uniform(k_fav, (NUM_CONTEXTS,))))
        start = jnp.take(fields["cycle"][0], pick(jax.random.uniform(k_start, (1,))))
        u = jax.random.uniform(k_path, (hours - 1, 1))
        later = sample_paths({**fields, "favourite": favourite[None]}, start, 0, u, alone)
        return jnp.concatenate([start, later[:, 0]])

    return jax.jit(jax.vmap(path))(jax.random.split(key, num))


def test_history_posterior_matches_rejection_sampling_of_the_generator(homes):
    """Sample whole paths (favourites redrawn), keep those that match the observed window, and
    compare where they are at τ_q with the posterior. The queries are the ones where the window
    -only formula (issue 46) is furthest off; it must be rejected, the posterior accepted."""
    regime, valid, num = (np.asarray(a) for a in (homes.regime, homes.object_valid,
                                                  homes.num_allowed))
    e, m = (int(i[0]) for i in np.nonzero((regime == REGIMES.index("preferences")) & valid
                                          & (num == 3)))
    home = homes.home(e)
    draws = np.asarray(_redrawn_paths(jax.random.key(46), home, m, 118, 60_000, CONFIG))
    seen = np.asarray(home.receptacle[:, m])
    for tau, tau_q, history in ((63, 66, 1), (105, 117, 3)):
        keep = np.all(draws[:, tau - history + 1:tau + 1] == seen[tau - history + 1:tau + 1],
                      axis=1)
        freq = np.bincount(draws[keep, tau_q], minlength=seen.max() + 1).astype(np.float64)
        accepted = keep.sum()
        assert accepted > 1000, accepted
        freq = np.pad(freq, (0, CONFIG.max_receptacles - freq.size)) / accepted
        p = np.asarray(homes_history_posterior(home, m, tau, tau_q, history, CONFIG), np.float64)
        se = np.sqrt(np.maximum(p * (1 - p), 1e-12) / accepted)
        assert np.all(np.abs(freq - p) <= 4 * se + 1e-4), (tau, freq, p)
        window_only, cycle = _enumerated_posteriors(home, m, tau, tau_q, CONFIG, False,
                                                    first=[tau - history + 1])
        old = window_only[0]
        z = np.abs(freq[cycle] - old) / np.sqrt(old * (1 - old) / accepted)
        assert z.max() > 10, (freq[cycle], old)


def test_posterior_jit_vmap_and_traced_bad_queries(homes):
    e, m = _objects_by_regime(homes)[0]
    home = homes.home(e)
    taus, tau_qs = jnp.asarray([0, 10, 100, 150]), jnp.asarray([5, 11, 190, 151])
    batched = jax.vmap(lambda a, b: homes_posterior(home, m, a, b, CONFIG))(taus, tau_qs)
    for i in range(4):
        np.testing.assert_allclose(batched[i], homes_posterior(home, m, int(taus[i]),
                                                               int(tau_qs[i]), CONFIG),
                                   atol=1e-6)
    over_objects = jax.vmap(lambda i: homes_posterior(home, i, 3, 9, CONFIG))(
        jnp.arange(CONFIG.max_objects))
    valid = np.asarray(home.object_valid)
    np.testing.assert_allclose(np.asarray(over_objects)[valid].sum(-1), 1.0, atol=1e-5)
    assert np.all(np.isnan(np.asarray(over_objects)[~valid]))
    over_homes = jax.vmap(lambda h: homes_posterior(h, 0, 3, 9, CONFIG))(homes)
    assert over_homes.shape == (NUM_HOMES, CONFIG.max_receptacles)
    bad = jax.jit(lambda a, b: homes_posterior(home, m, a, b, CONFIG))(jnp.int32(9), jnp.int32(9))
    assert np.all(np.isnan(bad))


@pytest.mark.parametrize(("args", "message"), [
    ((0, 10, 10), r"tau_q must lie in 11\.\."),
    ((0, 10, 5), r"tau_q must lie in 11\.\."),
    ((0, 10, 192), "tau_q"),
    ((0, -1, 5), "tau"),
    ((15, 0, 5), "object_index"),
    ((0, 1.5, 5), "tau"),
])
def test_bad_queries_name_the_argument(homes, args, message):
    e, m = _objects_by_regime(homes)[0]
    obj, tau, tau_q = args
    with pytest.raises(ValueError, match=message):
        homes_posterior(homes.home(e), obj if obj == 15 else m, tau, tau_q, CONFIG)


def test_bad_history_and_home(homes):
    home = homes.home(0)
    m = int(np.flatnonzero(np.asarray(home.object_valid))[0])
    with pytest.raises(ValueError, match="history"):
        homes_history_posterior(home, m, 5, 9, 7, CONFIG)
    with pytest.raises(ValueError, match="history"):
        homes_history_posterior(home, m, 5, 9, 0, CONFIG)
    with pytest.raises(ValueError, match=r"homes\.receptacle has shape"):
        homes_posterior(homes.home(0).replace(receptacle=home.receptacle[:10]), m, 0, 5,
                        CONFIG)
    with pytest.raises(ValueError, match="homes must be a Homes"):
        homes_posterior({"receptacle": home.receptacle}, m, 0, 5, CONFIG)


# ---------------------------------------------------------------------------- files


def test_save_load_round_trip(homes, tmp_path):
    path = tmp_path / "homes.npz"
    side = save_homes(path, homes, CONFIG)
    assert side == schema_path(path) and side.name == "homes.schema.json"
    schema = json.loads(side.read_text())
    assert set(schema["fields"]) == set(FIELDS)
    assert schema["fields"]["receptacle"]["sizes"] == [NUM_HOMES, CONFIG.num_hours,
                                                       CONFIG.max_objects]
    loaded, config = load_homes(path)
    assert config == CONFIG
    for a, b in zip(jax.tree.leaves(homes), jax.tree.leaves(loaded), strict=True):
        np.testing.assert_array_equal(a, b)


def _write(path, arrays):
    np.savez(path, **arrays)
    return path


def test_load_refuses_bad_files(homes, tmp_path):
    good = tmp_path / "good.npz"
    save_homes(good, homes, CONFIG)
    with np.load(good) as f:
        arrays = {k: f[k] for k in f.files}
    cases = {
        "missing": ({k: v for k, v in arrays.items() if k != "favourite"}, "missing arrays"),
        "shape": ({**arrays, "receptacle": arrays["receptacle"][:, :5]}, "receptacle has shape"),
        "dtype": ({**arrays, "regime": arrays["regime"].astype(np.int64)}, "regime has shape"),
        "version": ({**arrays, "format_version": np.int64(99)}, "format_version"),
        "schema": ({**arrays, "schema_json": np.asarray(json.dumps({"format": "x"}))},
                   "schema_json"),
        "nan": ({**arrays, "room_box": np.where(arrays["room_box"] > 5, np.nan,
                                                arrays["room_box"]).astype(np.float32)},
                "room_box contains NaN"),
        "range": ({**arrays, "receptacle": np.where(arrays["receptacle"] >= 0, 17,
                                                    arrays["receptacle"]).astype(np.int32)},
                  "receptacle must be an allowed"),
        "extra": ({**arrays, "pickle": np.zeros(2)}, "unexpected member"),
    }
    for name, (content, message) in cases.items():
        with pytest.raises(ValueError, match=message):
            load_homes(_write(tmp_path / f"{name}.npz", content))
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"not a readable \.npz"):
        load_homes(tmp_path / "junk.npz")
    with pytest.raises(ValueError, match="does not exist"):
        load_homes(tmp_path / "absent.npz")
    (tmp_path / "link.npz").symlink_to(good)
    with pytest.raises(ValueError, match="symbolic link"):
        save_homes(tmp_path / "link.npz", homes, CONFIG)


def test_receptacle_class_vocabulary_is_data():
    """A new receptacle and object class are a change of data only."""
    base = HomesConfig()
    shelf = ReceptacleClass("wall_shelf", "wall shelf", (0.8, 0.3, 1.2), ("bathroom",))
    plant = ObjectClass("plant", "potted plant", (0.2, 0.2, 0.4), ("wall_shelf",))
    config = HomesConfig(receptacle_classes=(*base.receptacle_classes, shelf),
                         object_classes=(*base.object_classes, plant), num_hours=24)
    assert config.vocabulary[-1] == "potted plant"
