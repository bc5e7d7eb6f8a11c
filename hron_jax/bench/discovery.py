"""Object discovery distance per category and camera resolution (`python -m hron_jax.bench discovery`).

Measures, for every object category that houses contain (vocabulary.HOUSE_OBJECTS; the symbolic
circle / triangle exist only in the 2D choice task), how far away the graph builder first adds the
object's node when the agent walks straight at it. Scene: built here (hron_jax.scenes.mjcf), one
12 x 6 m room, a table (top at 0.75 m) and one pool object per category; the object lies at the
centre of the table top (--support table, the onTop relation) or on the floor (--support floor),
and nothing stands between it and the agent. Agent: the default camera (CameraConfig: 120 deg
vertical FoV, 1 m above the floor, no pitch) at each --sizes resolution, facing the object, at xy
distances d from 7 m down to 0.3 m on a geometric grid (1 % steps). Every frame goes through
GraphBuilder.update (from an empty graph), once per rule:
    frame px   GraphConfig(pixel_reference=None): min_pixels pixels of the frame itself
               (the rule before pixel_reference existed)
    ref px     GraphConfig() (pixel_reference=128, the default): frame_min_pixels(W, H) pixels,
               the area of min_pixels pixels of the paper's 128 x 128 frame, at least 1
(a column per distinct threshold; at 128 x 128 both rules need min_pixels).

Discovery sees the renderer's point samples: an object smaller than a pixel shows up only where it
covers a pixel centre, so the distance depends on where it falls between pixel centres. Each
approach is therefore repeated at --phases x --phases sub-pixel view offsets of that resolution's
pixel (yaw over half a pixel, the view being mirror-symmetric; pitch, as a world rotation about
the camera's right axis, over a whole one). A cell is the median [min-max] over the offsets of the
largest d at which the node was discovered (the first discovery of a real approach), in metres;
the success radius of the navigation tasks is 1 m. In parentheses: the geometric prediction, the
largest d at which the object's expected pixel count (its silhouette for that view direction over
the area of a pixel on the image plane at its off-axis angle) reaches the threshold. Measured
first discoveries lie beyond it: the count of one frame scatters around that mean, and a thin
object (laptop, book) covers a whole row of pixel centres at once when a row passes through it.

Prints: scene and settings, then the Markdown table | object | half extents (cm) | one column per
(size, threshold) |, a row per category as soon as it is measured (2.3 min on 2 shared EPYC cores
at load average 8, 1 min of CPU time). Approaches are rendered far to near and stop once every
offset has seen the object.
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ..graph_builder import GraphBuilder, GraphConfig, Placement
from ..scenes import mjcf
from ..scenes import vocabulary as V
from ..scenes.loader import scene_from_model
from ..sensors import Camera, CameraConfig, camera_frame
from .common import progress, stream_table

TABLE_XY = (0.0, 0.0)  # table centre; its top spans x in [-0.4, 0.4] (yaw 90: depth along x)
FLOOR_XY = (0.0, 2.0)  # a floor object, 2 m beside the table
D_MAX, D_MIN, D_RATIO = 7.0, 0.3, 1.01


def bench_scene():
    """The bench scene (Scene) and its MJCF text: one room, one table, one object per house category."""
    w = mjcf.SceneWriter("discovery_bench", "hron_jax.bench.discovery: one table, one object per category")
    w.add_room("living_room", [(-9.0, -3.0, 3.0, 3.0)])
    w.add_furniture("table", *TABLE_XY, yaw=90.0)
    w.add_start(-5.0, 0.0)
    w.add_object_pool({c: 1 for c in V.HOUSE_OBJECTS})
    xml = w.xml()
    return scene_from_model(mujoco.MjModel.from_xml_string(xml), "<discovery bench scene>"), xml


def object_position(category: str, support: str) -> np.ndarray:
    half = V.OBJECT_SHAPES[category].half
    if support == "table":
        return np.array([TABLE_XY[0], TABLE_XY[1], 0.75 + half[2]])
    return np.array([FLOOR_XY[0], FLOOR_XY[1], half[2]])


def distances() -> np.ndarray:
    """xy distances of the approach, far to near."""
    n = int(math.floor(math.log(D_MAX / D_MIN) / math.log(D_RATIO))) + 1
    return D_MAX / D_RATIO ** np.arange(n)


def projected_area(category: str, view: np.ndarray) -> np.ndarray:
    """Silhouette area (m^2) of the category's primitive seen along unit directions view (..., 3)."""
    s = V.OBJECT_SHAPES[category]
    vx, vy, vz = (np.abs(view[..., i]) for i in range(3))
    if s.geom == "sphere":
        return np.full(vx.shape, math.pi * s.size[0] ** 2)
    if s.geom == "capsule":  # disk + the axis segment's shadow (axis along z)
        r, hl = s.size
        return math.pi * r**2 + 4 * r * hl * np.sqrt(np.maximum(0.0, 1 - vz**2))
    hx, hy, hz = s.size
    return 4 * (hy * hz * vx + hx * hz * vy + hx * hy * vz)


def predicted_pixels(category: str, pos: np.ndarray, d: np.ndarray, cam: CameraConfig) -> np.ndarray:
    """Expected pixel count of the object from xy distance d, straight ahead (pinhole, no pitch):
    silhouette / range^2 is its solid angle; on the image plane (focal 1) that is / cos^3 of the
    off-axis angle; one pixel covers (2 tan(vfov/2) / H)^2 there."""
    dz = cam.mount_height - pos[2]
    rng = np.hypot(d, dz)
    view = np.stack([d / rng, np.zeros_like(d), dz / rng], -1)
    image_area = projected_area(category, view) * rng / d**3
    return image_area / ((2 * cam.tan_v / cam.height) * (2 * cam.tan_h / cam.width))


def _pitch_world(xpos, xmat, pose, cfg, beta):
    """Geom poses rotated by beta about the camera's right axis through its origin: the view of a
    camera pitched by -beta (a sub-pixel vertical offset without a new Camera)."""
    o, rot = camera_frame(pose, cfg)
    r = rot[:, 0]
    k = jnp.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    R = jnp.eye(3) + jnp.sin(beta) * k + (1 - jnp.cos(beta)) * (k @ k)
    return o + (xpos - o) @ R.T, jnp.einsum("ij,gjk->gik", R, xmat.reshape(-1, 3, 3))


def first_discovery(flags: np.ndarray, d: np.ndarray) -> np.ndarray:
    """flags bool[..., D] over the far-to-near grid d -> largest d with a discovery (nan: never)."""
    any_ = flags.any(-1)
    first = np.argmax(flags, -1)
    return np.where(any_, d[first], np.nan)


def _rules(min_pixels: int) -> dict[str, GraphConfig]:
    return {
        "frame": GraphConfig(min_pixels=min_pixels, pixel_reference=None),
        "ref": GraphConfig(min_pixels=min_pixels),
    }


def columns(sizes, min_pixels: int) -> list[tuple[int, int]]:
    """The table's (size, threshold in frame pixels) columns: one per distinct threshold."""
    out = []
    for s in sizes:
        for g in _rules(min_pixels).values():
            if (s, g.frame_min_pixels(s, s)) not in out:
                out.append((s, g.frame_min_pixels(s, s)))
    return out


def bench_discovery(
    sizes=(32, 64, 128), support: str = "table", phases: int = 4, min_pixels: int = 2, chunk: int = 8
):
    """Yields one row per house object category: {category, half, cells: {(size, threshold):
    (first-discovery distances f64[phases^2], predicted distance)}}, each as soon as it is measured.

    The approach is rendered far to near, `chunk` distances x phases^2 frames per call, and stops
    once every phase has discovered the object under every rule (nearer frames cannot change a
    first discovery)."""
    scene, _ = bench_scene()
    d = distances()
    rules = _rules(min_pixels)
    builders = [GraphBuilder(scene, g) for g in rules.values()]
    o0 = scene.num_rooms + scene.num_furniture
    # Sub-pixel offsets in pixels of each size: vertical over a whole pixel; horizontal over half
    # of one, since the view is mirror-symmetric about the approach line (offsets u and -u agree).
    u_h = (np.arange(phases) + 0.5) / (2 * phases)
    u_v = (np.arange(phases) + 0.5) / phases - 0.5

    cams = {}
    for s in sizes:
        cfg = CameraConfig(width=s, height=s)
        cam = Camera(scene.model, cfg, scene.geom_instance, scene.geom_class)

        def flags_of(xpos, xmat, placement, node, poses, betas, cam=cam, cfg=cfg):
            def one(pose_beta):
                pose, b = pose_beta[:3], pose_beta[3]
                xp, xm = _pitch_world(xpos, xmat, pose, cfg, b)
                f = cam.render_geoms(xp, xm, pose)
                zero = jnp.zeros((builders[0].max_nodes,), bool)
                return jnp.stack(
                    [gb.update(zero, placement, pose, f.instance, f.depth)[node] for gb in builders]
                )

            return jax.lax.map(one, jnp.concatenate([poses, betas[:, None]], -1), batch_size=64)

        # one pixel's angle at the image centre, horizontally and vertically
        yaw = np.arctan(u_h * 2 * cfg.tan_h / s)
        beta = np.arctan(u_v * 2 * cfg.tan_v / s)
        cams[s] = (cfg, jax.jit(flags_of), *(a.ravel() for a in np.meshgrid(yaw, beta, indexing="ij")))

    model = scene.model
    for cat in V.HOUSE_OBJECTS:
        node = scene.index_of(f"object:{cat}:0")
        pos = object_position(cat, support)
        data = mujoco.MjData(model)  # every other object parked under the floor
        data.mocap_pos[scene.mocap_id[node]] = pos
        mujoco.mj_forward(model, data)
        xpos = jnp.asarray(data.geom_xpos, jnp.float32)
        xmat = jnp.asarray(data.geom_xmat, jnp.float32)
        active = np.zeros(scene.num_objects, bool)
        active[node - o0] = True
        placement = Placement.empty(scene.num_objects)._replace(
            active=jnp.asarray(active), pos=jnp.zeros((scene.num_objects, 3)).at[node - o0].set(pos)
        )
        cells = {}
        for s in sizes:
            cfg, fn, yaw, beta = cams[s]
            flags = np.zeros((len(rules), len(yaw), len(d)), bool)  # (rule, phase, distance)
            t0, done = time.perf_counter(), 0
            while done < len(d) and not flags.any(-1).all():
                idx = np.minimum(np.arange(done, done + chunk), len(d) - 1)  # pad: repeat the last
                dd = np.repeat(d[idx][None], len(yaw), 0)  # (phase, distance)
                poses = np.stack(
                    [pos[0] - dd, np.full_like(dd, pos[1]), np.repeat(yaw[:, None], chunk, 1)], -1
                )
                betas = np.repeat(beta[:, None], chunk, 1)
                out = fn(
                    xpos,
                    xmat,
                    placement,
                    node,
                    jnp.asarray(poses.reshape(-1, 3), jnp.float32),
                    jnp.asarray(betas.ravel(), jnp.float32),
                )
                flags[:, :, idx] |= np.asarray(out).reshape(len(yaw), chunk, len(rules)).transpose(2, 0, 1)
                done += chunk
            frames = min(done, len(d)) * len(yaw)
            progress(f"{cat} {s}x{s}: {frames} frames in {time.perf_counter() - t0:.1f} s")
            pred_px = predicted_pixels(cat, pos, d, cfg)
            in_range = d < rules["frame"].detect_range
            for k, g in enumerate(rules.values()):
                thr = g.frame_min_pixels(s, s)
                if (s, thr) in cells:
                    continue
                ok = (pred_px >= thr) & in_range
                pred = d[np.argmax(ok)] if ok.any() else np.nan
                cells[(s, thr)] = (first_discovery(flags[k], d), pred)
        yield dict(category=cat, half=V.OBJECT_SHAPES[cat].half, cells=cells)


def _cell(dists, pred) -> str:
    f = lambda x: "-" if np.isnan(x) else f"{x:.2f}"
    if np.isnan(dists).all():
        return f"- ({f(pred)})"
    lo, med, hi = np.nanmin(dists), np.nanmedian(dists), np.nanmax(dists)
    miss = int(np.isnan(dists).sum())
    return f"{med:.2f} [{lo:.2f}-{hi:.2f}]{f' ({miss} never)' if miss else ''} ({f(pred)})"


def header(columns) -> str:
    names = [f"{s}² ≥{t} px" for s, t in columns]
    return "| object | half extents (cm) | " + " | ".join(names) + " |\n|---|---|" + "--:|" * len(names)


def format_row(r: dict) -> str:
    half = "x".join(f"{100 * h:g}" for h in r["half"])
    cells = " | ".join(_cell(*c) for c in r["cells"].values())
    return f"| {r['category']} | {half} | {cells} |"


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128], help="square camera sizes")
    p.add_argument("--support", choices=("table", "floor"), default="table")
    p.add_argument("--phases", type=int, default=4, help="sub-pixel offsets per image axis")
    p.add_argument("--min-pixels", type=int, default=2, help="GraphConfig.min_pixels of both rules")
    p.add_argument("--chunk", type=int, default=8, help="distances rendered per call (x phases^2 frames)")


def run(a: argparse.Namespace) -> None:
    d = distances()
    print(
        f"scene: built in hron_jax/bench/discovery.py; object on the {a.support}; camera "
        f"{CameraConfig().vfov_deg:g} deg vertical FoV at {CameraConfig().mount_height:g} m; "
        f"{len(d)} distances {d[0]:g}-{d[-1]:.2f} m (1 % steps) x {a.phases}x{a.phases} sub-pixel phases; "
        f"min_pixels {a.min_pixels}, detect_range {GraphConfig().detect_range:g} m",
        flush=True,
    )
    print(
        "cells: xy distance (m) of first discovery, median [min-max] over phases (geometric prediction)",
        flush=True,
    )
    rows = bench_discovery(tuple(a.sizes), a.support, a.phases, a.min_pixels, a.chunk)
    stream_table(header(columns(a.sizes, a.min_pixels)), rows, format_row)
