"""CLI: `python -m hron_jax.scenes --seed S --out scenes/house_S.xml` writes one generated house;
`python -m hron_jax.scenes --all [--dir scenes]` rewrites every shipped scene; `--plot DIR` also
renders top-down PNGs of what was written.
"""

from __future__ import annotations

import argparse
import os
import sys

from .generator import generate_house
from .houses import SHIPPED
from .loader import load_scene


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hron_jax.scenes", description=__doc__)
    ap.add_argument("--seed", type=int, help="generate one house from this seed")
    ap.add_argument("--out", help="output path for --seed (default scenes/house_<seed>.xml)")
    ap.add_argument("--all", action="store_true", help="rewrite every shipped scene")
    ap.add_argument("--dir", default="scenes", help="directory for --all")
    ap.add_argument("--plot", metavar="DIR", help="write top-down PNGs of the written scenes here")
    args = ap.parse_args(argv)
    if args.seed is None and not args.all:
        ap.error("give --seed S or --all")
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
            f"{scene.room_area().sum():.1f} m2, {scene.num_slots} slots, {len(scene.goals)} goal tuples"
        )
        if args.plot:
            from .plot import save_topdown

            os.makedirs(args.plot, exist_ok=True)
            save_topdown(scene, os.path.join(args.plot, os.path.basename(path).replace(".xml", ".png")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
