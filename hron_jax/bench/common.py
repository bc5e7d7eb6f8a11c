"""Shared by the benchmarks: the machine a measurement ran on, timing, and streamed tables.

Measures nothing itself. `machine()` / `machine_info()` describe the machine (hron_jax.reproduction
records `machine()` with every run; every subcommand prints `machine_info()` first and the load
average last); `timed` / `best_time` / `time_calls` time jitted calls (results blocked, best of
`repeats`, since the machine may be shared); `stream_table` prints a Markdown table row by row the
moment each row is measured (flush), so a run stopped early still shows what it measured; compile
times and other progress lines go to stderr (`progress`) so that the table on stdout stays whole.
Importing this module imports no JAX (reproduce.py --plan runs on bare machines).
"""

from __future__ import annotations

import os
import platform
import sys
import time
from collections.abc import Callable, Iterable

from hron_jax.paths import DEFAULT_SCENES

DEFAULT_SCENE = DEFAULT_SCENES["exploratory"]


def machine() -> dict:
    """The machine a measurement ran on: CPU model, logical / usable cores, 1-min load averages,
    Python, and (where JAX imports) its version and devices."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    out = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
    }
    if hasattr(os, "getloadavg"):
        out["loadavg"] = [round(x, 2) for x in os.getloadavg()]
    try:
        import jax

        out["jax"] = jax.__version__
        out["devices"] = [str(d) for d in jax.devices()]
        out["device_kind"] = f"{jax.devices()[0].platform} ({jax.devices()[0].device_kind})"
    except Exception:  # a report without JAX (e.g. reproduce.py --plan on a bare machine)
        pass
    return out


def machine_info() -> str:
    m = machine()
    load = ", load avg {:.1f} {:.1f} {:.1f}".format(*m["loadavg"]) if "loadavg" in m else ""
    return (
        f"CPU: {m['cpu']}, {m['cores']} logical cores ({m['usable_cores']} usable){load}; "
        f"jax {m.get('jax', '?')} on {m.get('device_kind', '?')}"
    )


def print_load() -> None:
    if hasattr(os, "getloadavg"):
        print("load avg at the end: {:.1f} {:.1f} {:.1f}".format(*os.getloadavg()), flush=True)


def progress(*args) -> None:
    """A progress line (compile times, ...) on stderr, flushed."""
    print(*args, file=sys.stderr, flush=True)


def timed(thunk: Callable):
    """(result, wall seconds) of thunk(), its result blocked until ready."""
    import jax

    t = time.perf_counter()
    out = jax.block_until_ready(thunk())
    return out, time.perf_counter() - t


def best_time(thunk: Callable, repeats: int) -> float:
    """Best wall seconds of thunk() over `repeats` calls."""
    return min(timed(thunk)[1] for _ in range(repeats))


def time_calls(fn: Callable, args_seq, repeats: int) -> float:
    """Best-of-`repeats` mean seconds per call of fn over args_seq (results blocked at the end)."""

    def run():
        out = None
        for a in args_seq:
            out = fn(*a)
        return out

    return best_time(run, repeats) / len(args_seq)


def stream_table(header: str, rows: Iterable[dict], fmt: Callable[[dict], str]) -> list[dict]:
    """Print `header` before the first row, then fmt(row) for each row as `rows` yields it (flushed);
    return the rows."""
    out = []
    for r in rows:
        if not out:
            print(header, flush=True)
        print(fmt(r), flush=True)
        out.append(r)
    return out


def random_placement(scene, batch: int, rng):
    """Every pool object of `scene` at the centre of a random relation slot, in `batch` envs:
    (pos f64[batch, objects, 3], batched graph_builder.Placement)."""
    import jax.numpy as jnp
    import numpy as np

    from ..graph_builder import Placement
    from ..scenes import vocabulary as V

    half = V.OBJECT_HALF[scene.vocab_index[scene.num_rooms + scene.num_furniture :]]
    slot = rng.integers(scene.num_slots, size=(batch, scene.num_objects))
    support = scene.slot_center[:, 2] - scene.slot_half[:, 2]
    pos = np.concatenate([scene.slot_center[slot, :2], (support[slot] + half[None, :, 2])[..., None]], -1)
    return pos, Placement(
        active=jnp.ones((batch, scene.num_objects), bool),
        pos=jnp.asarray(pos, jnp.float32),
        furniture=jnp.asarray(scene.slot_furniture[slot], jnp.int32),
        relation=jnp.asarray(scene.slot_relation[slot], jnp.int32),
    )
