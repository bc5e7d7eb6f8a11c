"""CLI: `python -m hron_jax.scenes --seed S --out scenes/house_S.xml` writes one generated house;
`python -m hron_jax.scenes --all [--dir scenes]` rewrites every shipped scene; `--plot DIR` also
renders top-down PNGs of what was written; `--stats SCENE [SCENE ...]` prints, per scene file, its
rooms, furniture, object pool, relation slots, goal tuples and the node count of a fully explored
graph in a typical exploratory episode (one episode sampled with PRNGKey(0) and the placement
sampler's defaults: target + DEFAULT_NUM_CLUTTER clutter objects, no distractors).
"""

from __future__ import annotations

import argparse
import os
import sys

from .generator import generate_house
from .houses import SHIPPED
from .loader import load_scene


def scene_stats(path: str, seed: int = 0, tables=None) -> dict:
    """Counts of a scene file and of one exploratory episode sampled with PRNGKey(seed) (the
    placement sampler's defaults). Keys: rooms, room_types, furniture, furniture_types, pool,
    slots, usable_slots, goals, static_nodes, active_objects, same_category (active objects of the
    goal's category besides the target), explored_nodes (rooms + furniture + active objects: the
    graph once everything is discovered), max_nodes (the graph's N_MAX: every pool object).
    tables: the scene's placement.EpisodeTables with the default settings if already built."""
    import jax
    import numpy as np

    from hron_jax.envs import placement as P
    from hron_jax.envs.table_cache import episode_tables
    from hron_jax.sim import Simulator

    scene = load_scene(path)
    if tables is None:
        tables = episode_tables(scene, Simulator.from_file(path).mj_model)
    ep = jax.jit(lambda k: P.sample_exploratory(k, tables))(jax.random.PRNGKey(seed))
    active = np.asarray(ep.placement.active)
    static = scene.num_rooms + scene.num_furniture
    goal_cat = int(ep.goal[0])
    return {
        "rooms": scene.num_rooms,
        "room_types": len(set(scene.vocab_index[: scene.num_rooms].tolist())),
        "furniture": scene.num_furniture,
        "furniture_types": len(set(scene.vocab_index[scene.num_rooms : static].tolist())),
        "pool": scene.num_objects,
        "slots": scene.num_slots,
        "usable_slots": int(tables.slot_usable.any(1).sum()),
        "goals": len(scene.goals),
        "static_nodes": static,
        "active_objects": int(active.sum()),
        "same_category": int((active & (tables.obj_cat == goal_cat)).sum()) - 1,
        "explored_nodes": static + int(active.sum()),
        "max_nodes": scene.num_nodes,
    }


def _print_stats(path: str) -> None:
    s = scene_stats(path)
    print(
        f"{path}: {s['rooms']} rooms ({s['room_types']} types), {s['furniture']} furniture "
        f"({s['furniture_types']} categories), object pool {s['pool']}, {s['slots']} relation slots "
        f"({s['usable_slots']} usable), {s['goals']} goal tuples; fully explored graph of a typical "
        f"exploratory episode (PRNGKey(0)): {s['explored_nodes']} nodes = {s['rooms']} + "
        f"{s['furniture']} + {s['active_objects']} objects ({s['same_category']} of the goal's category "
        f"besides the target); N_MAX {s['max_nodes']}"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hron_jax.scenes", description=__doc__)
    ap.add_argument("--seed", type=int, help="generate one house from this seed")
    ap.add_argument("--out", help="output path for --seed (default scenes/house_<seed>.xml)")
    ap.add_argument("--all", action="store_true", help="rewrite every shipped scene")
    ap.add_argument("--dir", default="scenes", help="directory for --all")
    ap.add_argument("--plot", metavar="DIR", help="write top-down PNGs of the written scenes here")
    ap.add_argument(
        "--stats",
        nargs="+",
        metavar="SCENE",
        help="print rooms, furniture, pool, slots and the fully explored node count of a typical "
        "episode of these scene files (after writing any)",
    )
    args = ap.parse_args(argv)
    if args.seed is None and not args.all and not args.stats:
        ap.error("give --seed S, --all or --stats SCENE")
    jobs = []
    if args.all:
        jobs += [(os.path.join(args.dir, name), fn) for name, fn in SHIPPED.items()]
    if args.seed is not None:
        jobs.append(
            (args.out or os.path.join("scenes", f"house_{args.seed}.xml"), lambda: generate_house(args.seed))
        )
    for path, fn in jobs:
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        with open(path, "w") as f:
            f.write(fn())
        scene = load_scene(path)  # refuse to leave a file behind that does not load
        print(
            f"{path}: {scene.num_rooms} rooms, {scene.num_furniture} furniture, {scene.model.ngeom} geoms, "
            f"{scene.room_area().sum():.1f} m2, {scene.num_slots} slots, {len(scene.goals)} goal tuples, "
            f"object pool {scene.num_objects}"
        )
        if args.plot:
            from .plot import save_topdown

            os.makedirs(args.plot, exist_ok=True)
            save_topdown(scene, os.path.join(args.plot, os.path.basename(path).replace(".xml", ".png")))
    for path in args.stats or ():
        _print_stats(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
