"""The homes vocabulary, as data: room types, receptacle classes (a size (w, d, h) in metres and
their room types) and object classes (a size and the receptacle classes they may stand on).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class RoomType:
    """A room type: ``name`` (identifier) and ``text`` (its descriptor)."""

    name: str
    text: str


@dataclasses.dataclass(frozen=True)
class ReceptacleClass:
    """A receptacle class: typical ``size`` (w, d, h) in metres, the room types it may be in."""

    name: str
    text: str
    size: tuple[float, float, float]
    rooms: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class ObjectClass:
    """A dynamic object class: ``size`` (w, d, h) in metres, the receptacle classes it may
    stand on."""

    name: str
    text: str
    size: tuple[float, float, float]
    receptacles: tuple[str, ...]


ROOM_TYPES = (
    RoomType("kitchen", "kitchen"),
    RoomType("living_room", "living room"),
    RoomType("bedroom", "bedroom"),
    RoomType("bathroom", "bathroom"),
    RoomType("office", "home office"),
    RoomType("dining_room", "dining room"),
)

RECEPTACLE_CLASSES = (
    ReceptacleClass("countertop", "kitchen countertop", (1.8, 0.6, 0.9), ("kitchen",)),
    ReceptacleClass("fridge", "fridge", (0.8, 0.7, 1.8), ("kitchen",)),
    ReceptacleClass("kitchen_sink", "kitchen sink", (0.8, 0.6, 0.9), ("kitchen",)),
    ReceptacleClass("dining_table", "dining table", (1.6, 0.9, 0.75),
                    ("dining_room", "kitchen")),
    ReceptacleClass("sofa", "sofa", (2.0, 0.9, 0.8), ("living_room",)),
    ReceptacleClass("coffee_table", "coffee table", (1.1, 0.6, 0.45), ("living_room",)),
    ReceptacleClass("tv_stand", "TV stand", (1.5, 0.45, 0.55), ("living_room", "bedroom")),
    ReceptacleClass("bookshelf", "bookshelf", (0.9, 0.35, 1.8),
                    ("living_room", "office", "bedroom")),
    ReceptacleClass("bed", "bed", (1.6, 2.0, 0.55), ("bedroom",)),
    ReceptacleClass("nightstand", "nightstand", (0.5, 0.4, 0.55), ("bedroom",)),
    ReceptacleClass("dresser", "dresser", (1.2, 0.5, 0.8), ("bedroom",)),
    ReceptacleClass("desk", "desk", (1.3, 0.7, 0.75), ("office", "bedroom")),
    ReceptacleClass("armchair", "armchair", (0.85, 0.85, 0.9), ("living_room", "office")),
    ReceptacleClass("bathroom_counter", "bathroom counter", (1.2, 0.55, 0.85), ("bathroom",)),
    ReceptacleClass("bathtub", "bathtub", (1.7, 0.75, 0.55), ("bathroom",)),
    ReceptacleClass("towel_rack", "towel rack", (0.6, 0.25, 1.0), ("bathroom",)),
    ReceptacleClass("side_table", "side table", (0.5, 0.5, 0.6),
                    ("living_room", "bedroom", "office", "dining_room")),
    ReceptacleClass("sideboard", "sideboard", (1.6, 0.45, 0.85), ("dining_room", "living_room")),
)

OBJECT_CLASSES = (
    ObjectClass("mug", "coffee mug", (0.09, 0.09, 0.1),
                ("countertop", "kitchen_sink", "dining_table", "coffee_table", "desk",
                 "nightstand", "side_table")),
    ObjectClass("cup", "drinking cup", (0.08, 0.08, 0.12),
                ("countertop", "kitchen_sink", "dining_table", "coffee_table", "desk",
                 "side_table")),
    ObjectClass("plate", "plate", (0.26, 0.26, 0.03),
                ("countertop", "kitchen_sink", "dining_table", "sideboard")),
    ObjectClass("bowl", "bowl", (0.16, 0.16, 0.07),
                ("countertop", "kitchen_sink", "dining_table", "coffee_table", "fridge")),
    ObjectClass("apple", "apple", (0.08, 0.08, 0.08),
                ("countertop", "fridge", "dining_table", "coffee_table", "desk")),
    ObjectClass("bread", "loaf of bread", (0.3, 0.12, 0.12),
                ("countertop", "fridge", "dining_table")),
    ObjectClass("knife", "kitchen knife", (0.3, 0.03, 0.02),
                ("countertop", "kitchen_sink", "dining_table")),
    ObjectClass("spoon", "spoon", (0.17, 0.04, 0.02),
                ("countertop", "kitchen_sink", "dining_table", "coffee_table")),
    ObjectClass("water_bottle", "water bottle", (0.07, 0.07, 0.25),
                ("fridge", "countertop", "desk", "nightstand", "dining_table")),
    ObjectClass("remote", "TV remote", (0.05, 0.18, 0.02),
                ("sofa", "coffee_table", "tv_stand", "armchair", "side_table", "bed")),
    ObjectClass("book", "book", (0.15, 0.23, 0.03),
                ("bookshelf", "nightstand", "coffee_table", "desk", "bed", "sofa",
                 "side_table")),
    ObjectClass("laptop", "laptop", (0.33, 0.23, 0.02),
                ("desk", "sofa", "bed", "dining_table", "coffee_table")),
    ObjectClass("phone", "mobile phone", (0.07, 0.15, 0.01),
                ("nightstand", "desk", "sofa", "coffee_table", "countertop", "bed")),
    ObjectClass("keys", "set of keys", (0.08, 0.04, 0.02),
                ("sideboard", "side_table", "dresser", "countertop", "desk")),
    ObjectClass("wallet", "wallet", (0.11, 0.09, 0.02),
                ("dresser", "sideboard", "nightstand", "desk", "side_table")),
    ObjectClass("glasses", "pair of glasses", (0.14, 0.05, 0.04),
                ("nightstand", "desk", "coffee_table", "bathroom_counter", "side_table")),
    ObjectClass("pen", "pen", (0.14, 0.01, 0.01),
                ("desk", "bookshelf", "dining_table", "side_table")),
    ObjectClass("notebook", "notebook", (0.15, 0.21, 0.01),
                ("desk", "bookshelf", "dining_table", "coffee_table")),
    ObjectClass("towel", "towel", (0.4, 0.3, 0.05),
                ("towel_rack", "bathtub", "bathroom_counter", "bed", "dresser")),
    ObjectClass("soap", "bar of soap", (0.09, 0.06, 0.03),
                ("bathroom_counter", "bathtub", "kitchen_sink")),
    ObjectClass("toothbrush", "toothbrush", (0.19, 0.02, 0.02),
                ("bathroom_counter", "bathtub")),
    ObjectClass("pillow", "pillow", (0.5, 0.35, 0.12), ("bed", "sofa", "armchair")),
    ObjectClass("teddy_bear", "teddy bear", (0.25, 0.2, 0.3),
                ("bed", "sofa", "armchair", "bookshelf")),
    ObjectClass("newspaper", "newspaper", (0.3, 0.4, 0.01),
                ("coffee_table", "dining_table", "sofa", "armchair", "side_table")),
    ObjectClass("vase", "flower vase", (0.12, 0.12, 0.3),
                ("sideboard", "dining_table", "coffee_table", "bookshelf", "side_table")),
    ObjectClass("candle", "candle", (0.07, 0.07, 0.12),
                ("dining_table", "coffee_table", "sideboard", "bathtub", "nightstand")),
    ObjectClass("watch", "wrist watch", (0.04, 0.04, 0.01),
                ("nightstand", "dresser", "desk", "bathroom_counter")),
    ObjectClass("headphones", "headphones", (0.18, 0.16, 0.08),
                ("desk", "nightstand", "sofa", "bed", "bookshelf")),
)

DEFAULT_ROOMS = ("kitchen", "living_room", "bedroom", "bathroom", "office", "dining_room")
"""The room types of every home of the default config (shuffled over the floor plan's cells)."""
