"""Geodesic distance fields: rasterise + solve time (`python -m hron_jax.bench geodesic [STENCIL]`).

Measures hron_jax.geodesic on a demo house (`_demo_house_xml`: 5 x 3 rooms of 5 m x 5 m, one 1 m
doorway in every interior wall, offset from the centre so paths bend): the rasterisation of the
occupancy grid (--cell-size), then `distance_fields` to --targets random free cells (success radius
1 m) in one batched call with STENCIL directions (8, 16, 32 or 48), timed once including compile and
once more.

Prints two lines, each as soon as it is known: the grid (shape, cell size, free fraction, stencil,
targets), then `rasterise S | first call (compile + run) S | run S (ms/target) | rounds max / mean`.
"""

from __future__ import annotations

import argparse
import time

from .common import timed


def _demo_house_xml(
    nx: int = 5, ny: int = 3, room: float = 5.0, wall: float = 0.1, door: float = 1.0, height: float = 2.5
) -> str:
    """A house-sized MJCF (nx x ny rooms of room x room metres) with one doorway in every interior
    wall, offset from the centre so paths bend."""
    geoms = [
        f'<geom type="box" size="{nx * room / 2} {ny * room / 2} 0.05" '
        f'pos="{nx * room / 2} {ny * room / 2} -0.05"/>'
    ]
    hz, half_w = height / 2, wall / 2

    def walls(lines: int, cells: int, along_x: bool):
        """Walls on the grid lines k * room along x (else y), a door in each interior wall."""
        for k in range(lines + 1):
            for i in range(cells):
                a0, a1 = i * room, (i + 1) * room
                dc = a0 + (1.0 if (i + k) % 2 else room - 1.0 - door)
                for lo, hi in ((a0, dc), (dc + door, a1)) if 0 < k < lines else ((a0, a1),):
                    if hi > lo:
                        size, pos = ((hi - lo) / 2, half_w), ((lo + hi) / 2, k * room)
                        if not along_x:
                            size, pos = size[::-1], pos[::-1]
                        geoms.append(
                            f'<geom type="box" size="{size[0]} {size[1]} {hz}" pos="{pos[0]} {pos[1]} {hz}"/>'
                        )

    walls(ny, nx, True)  # horizontal walls, doors between rows
    walls(nx, ny, False)  # vertical walls
    body = "\n    ".join(geoms)
    return f'<mujoco><asset><material name="m"/></asset><worldbody>\n    {body}\n  </worldbody></mujoco>'


def bench_geodesic(num_targets: int = 100, cell_size: float = 0.1, stencil: int = 48) -> None:
    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    from ..geodesic import GridConfig, distance_fields, occupancy_grid, success_init

    model = mujoco.MjModel.from_xml_string(_demo_house_xml())
    t0 = time.perf_counter()
    grid = occupancy_grid(model, config=GridConfig(cell_size=cell_size))
    t_raster = time.perf_counter() - t0
    print(
        f"grid {grid.shape} at {cell_size} m ({np.asarray(grid.free).mean():.0%} free), "
        f"stencil {stencil}, {num_targets} targets",
        flush=True,
    )
    rng = np.random.default_rng(0)
    free_idx = np.argwhere(np.asarray(grid.free))
    pick = free_idx[rng.choice(len(free_idx), num_targets, replace=False)]
    targets = np.asarray(grid.cell_to_world(pick))
    init = jax.vmap(lambda t: success_init(grid, t, 1.0))(jnp.asarray(targets))
    fn = lambda s: distance_fields(
        grid.free,
        s,
        grid.cell_size,
        fine=grid.fine,  # noqa: E731
        stencil=stencil,
        return_rounds=True,
    )
    _, t_first = timed(lambda: fn(init)[0])
    (_, rounds), t_run = timed(lambda: fn(init))
    print(
        f"rasterise {t_raster:.3f} s | first call (compile + run) {t_first:.2f} s | "
        f"run {t_run:.2f} s ({1e3 * t_run / num_targets:.1f} ms/target) | "
        f"rounds max {int(rounds.max())} mean {float(rounds.mean()):.1f}",
        flush=True,
    )


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "stencil",
        nargs="?",
        type=int,
        default=48,
        choices=(8, 16, 32, 48),
        help="stencil directions (default 48)",
    )
    p.add_argument("--targets", type=int, default=100, help="distance fields in the batch")
    p.add_argument("--cell-size", type=float, default=0.1, help="grid cell size, metres")


def run(a: argparse.Namespace) -> None:
    bench_geodesic(a.targets, a.cell_size, a.stencil)
