"""FlowSimConfig: paper defaults, validation naming the field, JSON round trip, data-only
categories. No JAX compilation here."""

from __future__ import annotations

import dataclasses
import json

import pytest

from flowmaps_jax.flowsim import FlowSimConfig, FurnitureKind, ObjectCategory
from flowmaps_jax.flowsim.config import sim_params, sim_shape

CUP = ObjectCategory("cup", 6, "orange", "diamond", "office_desk", "left_to_right")


def test_defaults_are_the_papers():
    c = FlowSimConfig()
    assert (c.map_size, c.num_furniture, c.min_per_kind, c.num_timesteps, c.max_tokens) == (
        256, 10, 3, 20, 20)
    assert (c.table_min_frac, c.table_max_frac, c.object_frac, c.min_object_px) == (
        0.10, 0.25, 0.4, 5)
    assert c.transition_probs == (0.2, 0.7, 0.1)
    assert c.dynamics == "markov"
    assert c.table_side_range == (25, 64)
    table = {cat.name: (cat.descriptor, cat.colour, cat.shape, cat.furniture_kind, cat.ordering)
             for cat in c.categories}
    assert table == {
        "fork": (0, "red", "square", "kitchen_table", "clockwise"),
        "bottle": (1, "green", "circle", "dining_table", "counter_clockwise"),
        "remote": (2, "blue", "triangle", "office_desk", "top_to_bottom"),
    }
    kinds = {k.name: (k.descriptor, k.colour) for k in c.furniture_kinds}
    assert kinds == {"kitchen_table": (3, "black"), "office_desk": (4, "brown"),
                     "dining_table": (5, "purple")}
    assert c.num_objects == 3 and c.num_descriptors == 6 and c.num_kinds == 3


@pytest.mark.parametrize(("field", "kwargs"), [
    ("transition_probs", {"transition_probs": (0.5, 0.7, -0.2)}),
    ("transition_probs", {"transition_probs": (0.2, 0.7, 0.2)}),
    ("transition_probs", {"transition_probs": (0.5, 0.5)}),
    ("jitter_probs", {"jitter_probs": (0.1, 0.1, 0.1)}),
    ("map_size", {"map_size": 8}),
    ("map_size", {"map_size": 5000}),
    ("map_size", {"table_min_frac": 0.4, "table_max_frac": 0.5}),
    ("num_furniture", {"num_furniture": 8}),
    ("num_furniture", {"num_furniture": 0}),
    ("table_min_frac", {"table_min_frac": 0.3}),
    ("object_frac", {"object_frac": 1.5}),
    ("num_timesteps", {"num_timesteps": 1}),
    ("map_size", {"map_size": 256.0}),
    ("dynamics", {"dynamics": "brownian"}),
])
def test_invalid_values_raise_naming_the_field(field, kwargs):
    with pytest.raises(ValueError, match=field):
        FlowSimConfig(**kwargs)


def test_invalid_category_table_raises():
    bad_order = dataclasses.replace(CUP, ordering="zigzag")
    with pytest.raises(ValueError, match="ordering"):
        FlowSimConfig(categories=(*FlowSimConfig().categories, bad_order))
    bad_kind = dataclasses.replace(CUP, furniture_kind="sofa")
    with pytest.raises(ValueError, match="furniture kind"):
        FlowSimConfig(categories=(*FlowSimConfig().categories, bad_kind))
    bad_shape = dataclasses.replace(CUP, shape="blob")
    with pytest.raises(ValueError, match="shape"):
        FlowSimConfig(categories=(*FlowSimConfig().categories, bad_shape))
    clash = dataclasses.replace(CUP, descriptor=3)  # kitchen_table's id
    with pytest.raises(ValueError, match="descriptor 3 is used twice"):
        FlowSimConfig(categories=(*FlowSimConfig().categories, clash))
    with pytest.raises(ValueError, match="categories"):
        FlowSimConfig(categories=())


def test_fourth_category_is_data_only():
    c = FlowSimConfig(categories=(*FlowSimConfig().categories, CUP))
    assert c.num_objects == 4 and c.num_descriptors == 7
    assert c.category_kind_index == (0, 2, 1, 1)
    assert sim_shape(c).orderings[-1] == "left_to_right"
    # A new furniture kind is data too; it needs its min_per_kind pieces.
    sofa = FurnitureKind("sofa", 7, "grey")
    with pytest.raises(ValueError, match="num_furniture"):
        FlowSimConfig(furniture_kinds=(*FlowSimConfig().furniture_kinds, sofa))
    c = FlowSimConfig(furniture_kinds=(*FlowSimConfig().furniture_kinds, sofa), num_furniture=12)
    assert c.num_kinds == 4 and c.num_descriptors == 8


def test_dict_round_trip_is_json_and_exact():
    c = FlowSimConfig(map_size=300, dynamics="schedule_jitter",
                      categories=(*FlowSimConfig().categories, CUP))
    text = json.dumps(c.to_dict())
    back = FlowSimConfig.from_dict(json.loads(text))
    assert back == c and hash(back) == hash(c)
    with pytest.raises(ValueError, match="unknown fields"):
        FlowSimConfig.from_dict({**c.to_dict(), "colour_depth": 8})
    with pytest.raises(ValueError, match="map_size"):
        FlowSimConfig.from_dict({**c.to_dict(), "map_size": -1})


def test_configs_differing_in_numbers_share_a_shape():
    a, b = FlowSimConfig(), FlowSimConfig(map_size=300, transition_probs=(0.1, 0.8, 0.1))
    assert sim_shape(a) == sim_shape(b)
    assert sim_params(b)["map_size"] == 300
    assert sim_params(a)["side_lo"] == 25 and sim_params(a)["side_hi"] == 64
