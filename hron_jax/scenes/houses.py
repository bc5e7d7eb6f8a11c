"""The shipped scenes: hand-designed default house, the mirror-symmetric room, generated houses.

Role: functions returning MJCF text for every file under scenes/ (`SHIPPED`: file name -> builder),
so `python -m hron_jax.scenes --all` regenerates them bit for bit.

- default_house(): a 9-room, ~187 m^2 single-storey family home in the spirit of iGibson's
  Wainscott_0_int: day band (living room, dining room, kitchen, en-suite style connections) above a
  corridor, night band (master bedroom with en-suite bathroom, second bedroom, office, utility room)
  below it. Floor plan and wish lists are fixed by hand; positions come from the generator's placer
  with a fixed seed.
- symmetric_room(): the directed task's room, mirror-symmetric about x = 0 with a start on the plane.
"""

from __future__ import annotations

import numpy as np

from . import mjcf
from . import vocabulary as V
from .generator import Item, RoomSpec, build_house, generate_house, make_door

DEFAULT_HOUSE_SEED = 7
GENERATED_SEEDS = (1, 2, 3)


def default_house() -> str:
    W, H = 17.0, 11.0
    yc0, yc1 = 4.8, 6.4
    rooms = [
        RoomSpec("corridor", (0.0, yc0, W, yc1)),
        RoomSpec("living_room", (0.0, yc1, 6.5, H)),
        RoomSpec("dining_room", (6.5, yc1, 10.5, H)),
        RoomSpec("kitchen", (10.5, yc1, W, H)),
        RoomSpec("bedroom", (0.0, 0.0, 4.5, yc0)),
        RoomSpec("bathroom", (4.5, 0.0, 7.0, yc0)),
        RoomSpec("bedroom", (7.0, 0.0, 10.5, yc0)),
        RoomSpec("office", (10.5, 0.0, 14.0, yc0)),
        RoomSpec("utility_room", (14.0, 0.0, W, yc0)),
    ]
    rng = np.random.default_rng(DEFAULT_HOUSE_SEED)
    doors = [
        make_door(rooms, 1, 0, rng, 1.6, at=0.85),  # wide living room opening near the dining room
        make_door(rooms, 2, 0, rng, 1.2, at=0.5),
        make_door(rooms, 3, 0, rng, 1.0, at=0.1),
        make_door(rooms, 4, 0, rng, 1.0, at=0.9),
        make_door(rooms, 5, 0, rng, 1.0, at=0.5),
        make_door(rooms, 6, 0, rng, 1.0, at=0.2),
        make_door(rooms, 7, 0, rng, 1.0, at=0.8),
        make_door(rooms, 8, 0, rng, 1.0, at=0.5),
        make_door(rooms, 1, 2, rng, 1.2, at=0.4),
        make_door(rooms, 2, 3, rng, 1.2, at=0.5),
        make_door(rooms, 4, 5, rng, 1.0, at=0.2),  # en-suite bathroom
    ]
    wishes = [
        [Item("cabinet", sides="W", dims={"d": 0.35}), Item("shelf", sides="E", dims={"d": 0.3})],
        [
            Item("sofa", sides="W"),
            Item("coffee_table", "front", "sofa"),
            Item("tv_stand", "opposite", "sofa"),
            Item("shelf", sides="N"),
            Item("shelf", sides="N"),
            Item("cabinet", sides="S"),
        ],
        [
            Item("table", "centre", dims={"w": 1.8, "d": 0.9}),
            Item("cabinet", sides="N", dims={"w": 1.2}),
            Item("dresser", sides="EW"),
        ],
        [
            Item("fridge", sides="N"),
            Item("counter", sides="N", dims={"w": 2.0}),
            Item("sink_cabinet", sides="N"),
            Item("counter", sides="E", dims={"w": 2.0}),
            Item("cabinet", sides="E"),
            Item("shelf", sides="S"),
            Item("table", "centre", dims={"w": 1.2, "d": 0.8}),
        ],
        [
            Item("bed", sides="W", dims={"w": 1.6}),
            Item("nightstand", "beside", "bed"),
            Item("nightstand", "beside", "bed"),
            Item("wardrobe", sides="S", dims={"w": 1.6}),
            Item("dresser", sides="E"),
        ],
        [
            Item("sink_cabinet", sides="S"),
            Item("cabinet", sides="E", dims={"w": 0.6, "d": 0.35}),
            Item("shelf", sides="W", dims={"d": 0.3}),
        ],
        [
            Item("bed", sides="S", dims={"w": 1.0}),
            Item("nightstand", "beside", "bed"),
            Item("wardrobe", sides="E"),
            Item("desk", sides="W", dims={"w": 1.1, "d": 0.6}),
            Item("shelf", sides="W"),
        ],
        [
            Item("desk", sides="S", dims={"w": 1.5}),
            Item("shelf", sides="E"),
            Item("shelf", sides="E"),
            Item("cabinet", sides="W"),
            Item("table", "centre", dims={"w": 1.0, "d": 0.6}),
        ],
        [Item("counter", sides="S", dims={"w": 1.4}), Item("cabinet", sides="E"), Item("shelf", sides="W")],
    ]
    xml, _ = build_house(
        "house",
        rooms,
        doors,
        wishes,
        rng,
        starts=[(1.0, 5.6, 0.0)],
        comment="default HRON house, written by python -m hron_jax.scenes --all; "
        "edit hron_jax/scenes/houses.py, not this file",
    )
    return xml


def symmetric_room() -> str:
    """One 8 m x 6 m room, mirror plane x = 0: on each half a table and a shelf, exactly mirrored."""
    w = mjcf.SceneWriter(
        "symmetric_room",
        "directed-task room, mirror-symmetric about x = 0; written by python -m hron_jax.scenes --all",
    )
    x0, x1, y0, y1 = -4.0, 4.0, -3.0, 3.0
    w.add_room("living_room", [(x0, y0, x1, y1)])
    w.add_wall((x0, y0), (x1, y0))
    w.add_wall((x0, y1), (x1, y1))
    w.add_wall((x0, y0), (x0, y1))
    w.add_wall((x1, y0), (x1, y1))
    # Every furniture piece is symmetric about its own x = 0 plane, so mirroring a piece only
    # mirrors its position (yaw 0 for both).
    for sx in (-1.0, 1.0):
        w.add_furniture("table", 2.2 * sx, 0.0, 0.0)
    for sx in (-1.0, 1.0):
        w.add_furniture("shelf", 2.2 * sx, 2.77, 0.0)
    w.add_start(0.0, -2.0, 90.0)
    w.add_object_pool({o: 2 for o in V.HOUSE_OBJECTS})
    return w.xml()


SHIPPED = {
    "house.xml": default_house,
    "symmetric_room.xml": symmetric_room,
    **{f"house_{s}.xml": (lambda s=s: generate_house(s)) for s in GENERATED_SEEDS},
}
