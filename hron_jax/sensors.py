"""Agent camera by ray casting: depth, RGB, instance and semantic segmentation.

Role
----
A pinhole camera rides on the agent (pose (x, y, yaw) from the simulator), casts one ray per pixel
into the scene's geoms (boxes, spheres, capsules, with per-env poses from `mjx.Data`, so mocap
objects are where this env put them) and returns what the paper's agent sees:

    cam = Camera.for_simulator(sim, CameraConfig(width=32, height=32), scene=scene)
    out = cam.render(data, pose)            # one env; jax.vmap(cam.render) for a batch
    out.depth     f32[H, W]    z-depth along the optical axis (m), clipped to max_depth; miss = max_depth
    out.rgb       f32[H, W, 3] geom colour in [0, 1], Lambert-shaded by the hit normal; miss = 0
    out.instance  i32[H, W]    node index (Scene.geom_instance), -1 for nothing / structure
    out.semantic  i32[H, W]    class id (Scene.geom_class): 0 nothing, 1 structure, ...
    out.geom      i32[H, W]    MuJoCo geom id, -1 for nothing
    out.uncertain i32[]        rays whose result culling could not certify (0 = exact, see below)

Row 0 is the top of the image, column 0 the left. The agent's own geoms are never hit (as
mj_ray's bodyexclude), nor geoms with alpha 0 (as mj_ray).

Camera model: origin at the agent's (x, y) + `forward_offset` along the heading, at `mount_height`;
optical axis f along the heading tilted by `pitch_deg`; right r, up u = r x f. The ray of pixel
(i, j) is D = f + x_j tan(hfov/2) r + y_i tan(vfov/2) u with x_j, y_i the pixel-centre coordinates
in [-1, 1] and tan(hfov/2) = tan(vfov/2) W / H (square pixels). Because D has unit component along
f, the ray parameter of a hit *is* its z-depth (mj_ray returns distances in units of |vec| too).

Backends
--------
`backend="kernel"` (default): analytic ray-vs-primitive tests in JAX (slab method in the box frame;
quadratic for spheres; cylinder + two hemispheres for capsules), on a culled candidate set.
`backend="mjx"`: `mujoco.mjx.ray` per pixel (every ray tests every geom; reference / baseline).

Culling (why it is fast, and when it is exact)
---------------------------------------------
With no camera roll, all rays of one image column lie in one plane through the camera origin that
contains the camera's up axis u. Project everything onto the camera's (X, Z) plane (the plane
orthogonal to u): the column becomes a 2D ray (X, Z) = t (x_j tan(hfov/2), 1), and a geom's
projection is contained in the zonotope spanned by its (bounding-)box axes, i.e. the intersection of
three 2D slabs. A 2D slab test gives, per (column, geom), whether any ray of the column can hit the
geom (also requiring the geom's vertical extent to meet the column's vertical wedge within
max_depth) and a lower bound t_enter on the z-depth of any such hit (the hit's (X, Z) projection
lies in the footprint and on the column's 2D ray). Per column and per geom type we keep the K
candidates with smallest t_enter (`lax.top_k`, static shapes), then run the exact 3D kernel on H x K
pairs per column instead of H x G. Certificate: if more than K geoms passed in a column, the dropped
ones all have t_enter >= E, the largest kept t_enter; a ray whose found hit is at depth <= E is
therefore exact, and any other ray in an overflowing column counts in `uncertain`. With K large
enough for the scene (the tests check house views give uncertain == 0 and agree with mj_ray), the
kernel is exact; `uncertain > 0` says K is too small for that view. Nonzero pitch is supported (the
projection is then onto the tilted camera's X-Z plane); roll is not. Spheres and capsules are culled
the same way when a scene has more of them than k_sphere / k_capsule, else all are tested.

Row bands: a column's rows are split into `row_bands` bands (the last one padded), and each band
keeps the `k_band` of the column's K candidates with the smallest t_enter whose rows it may hold: a
hit of geom g in the column lies in its footprint interval [t_enter, t_exit] and in its bounding
box's vertical extent [Ylo, Yhi] (camera Y), so its row's slope y = Y / t is within [min, max] of Y
/ t over those intervals. The exact kernel then runs on H x k_band pairs per column. The certificate
composes: E of a band is the smaller of the column's and the band's. (Occlusion culling, i.e.
dropping candidates behind an upright box that covers the whole band, was built and measured: with
static sizes it saves no work, and it changes what is certified only when a band overflows because
of candidates behind its occluder; on house frames it certified the same rays (11 uncertain of
65,536 at 32x32 either way) at 28 % more render time, so it is not here.)

Measured on scenes/house.xml (281 boxes then, 311 now; 32 x 32, 120 deg, max_depth 10 m): boxes
passing the column test per column: mean 8.7, p99 23, max 43 over 300 random poses (inside furniture
included). k_box = 32 (default): 0 uncertain rays in 108 room-centre views, a few in 0.9% of
random-pose frames (8e-5 of all rays); k_box = 48: none in 320 random frames. In exploratory
episodes (64 envs, 30 random steps, 1,920 frames): per column 8.5 boxes on average (p99.9 32), at
most 2 spheres and 2 capsules (so k_sphere = k_capsule = 4); per band (8 bands of 4 rows) 2.1 boxes
(p99 12, p99.9 18, max 26) and at most 2 spheres / capsules. k_band = 12 (default) leaves exactly as
many uncertain rays in episode frames as one band per column: 29 of 655,360 in 640 frames at 32x32,
102 of 2.6 M in 160 frames at 128x128 (k_band = 8: 50 at 32x32); `bench env`'s random free poses,
some outside the house, show more (21 vs 9 in 64 frames at 32x32, 104 vs 0 in 16 at 128x128). CPU
cost at batch 64 (2-core EPYC, shared): ~50 ms per batch with culling vs ~240 ms testing every geom
and ~950 ms with mjx.ray. Row bands, the smaller sphere / capsule K and the shading in components
(below) together (2-core Xeon, one process, the same in-room frames): 31.2 -> 24.5 ms per 64 frames
at 32x32, 116.8 -> 61.4 ms per 16 frames at 128x128 (shading alone 12.6 -> 5.4 ms there); where both
certify, depth, geom, instance and class are identical and rgb within 1.2e-7. The generated houses
have more geoms per column: 111, 67 and 180 uncertain rays of 655,360 in 640 episode frames at 32x32
for house_1..3 (108, 67, 178 with one band per column); k_box = 48 takes house_3 to 2, at 40 instead
of 25 ms per 64 frames (XLA:CPU's top_k is much slower past k = 32).
XLA:CPU traps met on the way (each cost ~5-10x): components as separate arrays, not trailing axes
of size 3 (also in the shading: `_finish`); min and argmin as one variadic reduce; top_k values
used as a whole slice (see _column_candidates); the column scores materialised once
(optimization_barrier). A band's candidates are picked from the column's sorted ones by rank (a
cumsum and one comparison count per slot), not by a second top_k: as fast on the CPU, and no sort
and no one-hot table on any backend.

Shapes of the static tables: `geom_instance`, `geom_class` (ngeom,) int32 over the full model
(scene geoms first, then the agent's: use `Simulator.geom_tables`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

_BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
_SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_TYPES = (_BOX, _SPHERE, _CAPSULE)
_EPS = 1e-12


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Static camera settings (hashable)."""

    width: int = 32
    height: int = 32
    vfov_deg: float = 120.0  # the paper's camera (128 x 128, 120 deg vertical FoV); square pixels
    max_depth: float = 10.0  # m; farther hits read as misses
    mount_height: float = 1.0  # camera origin above the floor (m)
    forward_offset: float = 0.0  # camera origin ahead of the agent's axis (m)
    pitch_deg: float = 0.0  # + looks up
    backend: str = "kernel"  # "kernel" | "mjx"
    k_box: int = 32  # per-column candidates kept per geom type (see module docstring)
    k_sphere: int = 4  # house episodes: at most 2 spheres / 2 capsules per column (1,920 frames)
    k_capsule: int = 4
    row_bands: int = 8  # a column's rows are culled again in this many bands (see module docstring)
    k_band: int = 12  # candidates kept per band, out of the column's
    # how a column picks its k nearest candidates: "top_k" (lax.top_k: XLA:CPU's fast TopK call, a
    # full sort of every column's G scores on XLA:GPU) or "rank" (no sort: see _nearest_ranked)
    select: str = "top_k"
    ambient: float = 0.35  # Lambert shading: ambient + (1 - ambient) * max(0, n . l)
    light_dir: tuple = (0.3, 0.2, 1.0)  # world direction towards a distant light (plus a headlight)

    @property
    def tan_v(self) -> float:
        return math.tan(math.radians(self.vfov_deg) / 2)

    @property
    def tan_h(self) -> float:
        return self.tan_v * self.width / self.height


class CameraOutput(NamedTuple):
    depth: jax.Array
    rgb: jax.Array
    instance: jax.Array
    semantic: jax.Array
    geom: jax.Array
    uncertain: jax.Array


def effective_rgba(m: mujoco.MjModel) -> np.ndarray:
    """Per-geom colour as MuJoCo shows it: the material's rgba unless the geom overrides the default."""
    rgba = np.array(m.geom_rgba, np.float64)
    default = np.array([0.5, 0.5, 0.5, 1.0])
    has_mat = m.geom_matid >= 0
    use_mat = has_mat & np.all(np.isclose(rgba, default), axis=1)
    rgba[use_mat] = m.mat_rgba[m.geom_matid[use_mat]]
    return rgba


def camera_frame(pose: jax.Array, cfg: CameraConfig):
    """Camera origin o (3,) and rotation R (3, 3) whose columns are right, up, forward (world)."""
    x, y, yaw = pose[0], pose[1], pose[2]
    p = math.radians(cfg.pitch_deg)
    cy, sy = jnp.cos(yaw), jnp.sin(yaw)
    f = jnp.stack([cy * math.cos(p), sy * math.cos(p), jnp.full_like(cy, math.sin(p))])
    r = jnp.stack([sy, -cy, jnp.zeros_like(cy)])
    u = jnp.stack([-cy * math.sin(p), -sy * math.sin(p), jnp.full_like(cy, math.cos(p))])
    o = jnp.stack(
        [x + cfg.forward_offset * cy, y + cfg.forward_offset * sy, jnp.full_like(cy, cfg.mount_height)]
    )
    return o, jnp.stack([r, u, f], axis=1)


def pixel_directions(cfg: CameraConfig) -> np.ndarray:
    """(H, W, 3) ray directions in camera coordinates (X right, Y up, Z forward), Z component 1."""
    xs = (2.0 * (np.arange(cfg.width) + 0.5) / cfg.width - 1.0) * cfg.tan_h
    ys = (1.0 - 2.0 * (np.arange(cfg.height) + 0.5) / cfg.height) * cfg.tan_v
    d = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.ones((1, 1))), -1)
    return d.astype(np.float32)


def world_rays(pose: jax.Array, cfg: CameraConfig):
    """Ray origin (3,) and world directions (H, W, 3) for a pose; hit parameter = z-depth."""
    o, rot = camera_frame(pose, cfg)
    return o, jnp.einsum("ij,hwj->hwi", rot, jnp.asarray(pixel_directions(cfg)))


# ---------------------------------------------------------------------------------------------
# Exact ray-vs-primitive kernels in the geom's local frame. Components are passed separately
# (structure of arrays: px, py, pz, dx, dy, dz, each broadcastable): XLA's CPU backend vectorises
# long elementwise arrays well and trailing axes of size 3 badly (measured: ~4x). Each returns the
# smallest t >= 0 with p + t d on the surface, +inf if none; d need not be unit length.


def _safe_inv(d):
    return 1.0 / jnp.where(jnp.abs(d) < _EPS, jnp.where(d >= 0, _EPS, -_EPS), d)


def ray_box_soa(sx, sy, sz, px, py, pz, dx, dy, dz):
    """Slab method for a box of half sizes s centred at the local origin.

    An origin inside the box yields the exit distance (as mj_ray)."""
    t_lo, t_hi = None, None
    for s, p, d in ((sx, px, dx), (sy, py, dy), (sz, pz, dz)):
        inv = _safe_inv(d)
        ta = (-s - p) * inv
        tb = (s - p) * inv
        lo, hi = jnp.minimum(ta, tb), jnp.maximum(ta, tb)
        t_lo = lo if t_lo is None else jnp.maximum(t_lo, lo)
        t_hi = hi if t_hi is None else jnp.minimum(t_hi, hi)
    hit = t_hi >= jnp.maximum(t_lo, 0.0)
    return jnp.where(hit, jnp.where(t_lo >= 0.0, t_lo, t_hi), jnp.inf)


def _quad_roots(a, b, c):
    """Roots of a t^2 + 2 b t + c = 0 (small, large); NaN-free, +inf where no real root."""
    disc = b * b - a * c
    ok = (disc >= 0.0) & (a > _EPS)
    sq = jnp.sqrt(jnp.maximum(disc, 0.0))
    inv_a = 1.0 / jnp.where(a > _EPS, a, 1.0)
    return jnp.where(ok, (-b - sq) * inv_a, jnp.inf), jnp.where(ok, (-b + sq) * inv_a, jnp.inf)


def _first_nonneg(t0, t1):
    return jnp.where(t0 >= 0.0, t0, jnp.where(t1 >= 0.0, t1, jnp.inf))


def ray_sphere_soa(r, px, py, pz, dx, dy, dz):
    t0, t1 = _quad_roots(
        dx * dx + dy * dy + dz * dz, dx * px + dy * py + dz * pz, px * px + py * py + pz * pz - r * r
    )
    return _first_nonneg(t0, t1)


def ray_capsule_soa(r, h, px, py, pz, dx, dy, dz):
    """Capsule along local z: cylinder |z| <= h of radius r, hemispherical caps."""
    t0, t1 = _quad_roots(dx * dx + dy * dy, dx * px + dy * py, px * px + py * py - r * r)
    t = _first_nonneg(t0, t1)
    t = jnp.where(jnp.abs(pz + t * dz) <= h, t, jnp.inf)
    dd = dx * dx + dy * dy + dz * dz
    for sgn in (1.0, -1.0):  # each cap's roots count only on its own hemisphere
        qz = pz - sgn * h
        c0, c1 = _quad_roots(dd, dx * px + dy * py + dz * qz, px * px + py * py + qz * qz - r * r)
        for c in (c0, c1):
            on_cap = sgn * (pz + c * dz) >= h
            t = jnp.where(on_cap & (c >= 0.0) & (c < t), c, t)
    return t


def ray_box(size, p, d):
    """size, p, d (..., 3) -> t (...)."""
    return ray_box_soa(*jnp.moveaxis(size, -1, 0), *jnp.moveaxis(p, -1, 0), *jnp.moveaxis(d, -1, 0))


def ray_sphere(radius, p, d):
    """radius (...), p, d (..., 3) -> t (...)."""
    return ray_sphere_soa(radius, *jnp.moveaxis(p, -1, 0), *jnp.moveaxis(d, -1, 0))


def ray_capsule(radius, half_len, p, d):
    """radius, half_len (...), p, d (..., 3) -> t (...)."""
    return ray_capsule_soa(radius, half_len, *jnp.moveaxis(p, -1, 0), *jnp.moveaxis(d, -1, 0))


def _local_normal(gtype, size, q):
    """Outward unit normal at local surface point q = (qx, qy, qz) for the geom type (per element).

    Structure of arrays: size and q are 3-tuples of equally shaped arrays; returns a 3-tuple."""
    # box: the face whose normalised coordinate is largest (first axis on ties, as argmax)
    rel = [jnp.abs(qi) / jnp.maximum(si, _EPS) for qi, si in zip(q, size)]
    ax0 = (rel[0] >= rel[1]) & (rel[0] >= rel[2])
    ax1 = ~ax0 & (rel[1] >= rel[2])
    ax = (ax0, ax1, ~ax0 & ~ax1)
    n_box = [jnp.where(a, jnp.sign(qi), 0.0) for a, qi in zip(ax, q)]
    zc = jnp.clip(q[2], -size[1], size[1])
    n_cap = (q[0], q[1], q[2] - zc)
    box, sphere = gtype == _BOX, gtype == _SPHERE
    n = [jnp.where(box, nb, jnp.where(sphere, qs, nc)) for nb, qs, nc in zip(n_box, q, n_cap)]
    inv = 1.0 / jnp.maximum(jnp.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2), _EPS)
    return tuple(ni * inv for ni in n)


# ---------------------------------------------------------------------------------------------


class Camera:
    """Static camera tables for one model; `render` is pure and jittable (vmap for batches)."""

    def __init__(
        self,
        mj_model: mujoco.MjModel,
        config: CameraConfig = CameraConfig(),
        geom_instance: np.ndarray | None = None,
        geom_class: np.ndarray | None = None,
        exclude_body: int = -1,
        mjx_model: mjx.Model | None = None,
    ):
        m = mj_model
        cfg = config
        if cfg.backend not in ("kernel", "mjx"):
            raise ValueError(f"unknown backend {cfg.backend!r}")
        if cfg.select not in ("top_k", "rank"):
            raise ValueError(f"CameraConfig.select: unknown {cfg.select!r}; expected 'top_k' or 'rank'")
        self.config = cfg
        self.mj_model = m
        self.exclude_body = int(exclude_body)
        ng = m.ngeom
        self.geom_instance = jnp.asarray(
            np.full(ng, -1, np.int32) if geom_instance is None else np.asarray(geom_instance, np.int32)
        )
        self.geom_class = jnp.asarray(
            np.ones(ng, np.int32) if geom_class is None else np.asarray(geom_class, np.int32)
        )
        if self.geom_instance.shape != (ng,) or self.geom_class.shape != (ng,):
            raise ValueError(f"geom tables must have shape ({ng},); use Simulator.geom_tables")
        rgba = effective_rgba(m)
        self.geom_rgb = jnp.asarray(rgba[:, :3], jnp.float32)
        # same visibility filter as mj_ray / mjx.ray: alpha 0 geoms and the excluded body are skipped
        visible = rgba[:, 3] != 0
        if self.exclude_body >= 0:
            visible &= m.geom_bodyid != self.exclude_body
        self.geom_type = jnp.asarray(m.geom_type, jnp.int32)
        self.geom_size = jnp.asarray(m.geom_size, jnp.float32)
        self.type_ids = {}
        for t in _TYPES:
            ids = np.nonzero(visible & (m.geom_type == t))[0]
            if len(ids):
                self.type_ids[t] = ids
        other = np.nonzero(visible & ~np.isin(m.geom_type, _TYPES))[0]
        if len(other) and cfg.backend == "kernel":
            raise ValueError(f"kernel backend supports box/sphere/capsule only; geoms {other} are not")
        self._dirs_cam = pixel_directions(cfg)
        self._col_x = self._dirs_cam[0, :, 0]  # (W,) X slope of each column
        self._row_y = self._dirs_cam[:, 0, 1]  # (H,) Y slope of each row
        self._row_y_max = float(np.abs(self._row_y).max())
        # row bands: the last band is padded by repeating the last row (its extra rows are dropped)
        rows = -(-cfg.height // max(1, min(cfg.row_bands, cfg.height)))
        nb = -(-cfg.height // rows)
        band_y = np.concatenate([self._row_y, np.full(nb * rows - cfg.height, self._row_y[-1])])
        self._band_y = band_y.reshape(nb, rows).astype(np.float32)  # (nb, R) row slopes
        self._band_lo, self._band_hi = self._band_y.min(1), self._band_y.max(1)  # (nb,)
        if cfg.backend == "mjx":
            self.mjx_model = mjx_model if mjx_model is not None else mjx.put_model(m)
        light = np.asarray(cfg.light_dir, np.float64)
        self._light = jnp.asarray(light / np.linalg.norm(light), jnp.float32)

    @classmethod
    def for_simulator(
        cls, sim, config: CameraConfig = CameraConfig(), scene=None, geom_instance=None, geom_class=None
    ) -> Camera:
        """Camera for a `hron_jax.sim.Simulator`; tables from `scene` (a Scene) or given explicitly."""
        if scene is not None:
            geom_instance, geom_class = sim.geom_tables(scene.geom_instance, scene.geom_class)
        return cls(
            sim.mj_model,
            config,
            geom_instance,
            geom_class,
            exclude_body=sim.agent_body,
            mjx_model=sim.scene_mjx_model,  # the scene as it is; MJX steps only the blockers, grown
        )

    # ------------------------------------------------------------------ public API
    def render(self, data: mjx.Data, pose: jax.Array) -> CameraOutput:
        """One frame for one env from its data (geom poses) and agent pose (x, y, yaw)."""
        if self.config.backend == "mjx":
            return self._render_mjx(data, pose)
        return self.render_geoms(data.geom_xpos, data.geom_xmat, pose)

    def render_geoms(self, geom_xpos: jax.Array, geom_xmat: jax.Array, pose: jax.Array) -> CameraOutput:
        """Kernel backend from raw geom poses: geom_xpos (ngeom, 3), geom_xmat (ngeom, 9 or 3, 3)."""
        cfg = self.config
        o, rot = camera_frame(pose, cfg)
        xpos = geom_xpos.astype(jnp.float32)
        xmat = geom_xmat.reshape(-1, 3, 3).astype(jnp.float32)
        # every geom in camera coordinates: centre c (G, 3) and axes r[g, a, i] = camera comp a of axis i
        c_cam = (xpos - o) @ rot
        r_cam = jnp.einsum("ja,gji->gai", rot, xmat)
        nb, rows = self._band_y.shape
        X = jnp.asarray(self._col_x)[:, None, None, None]  # (W, 1, 1, 1) column slope
        Y = jnp.asarray(self._band_y)[None, :, :, None]  # (1, nb, R, 1) row slope per band

        kmax = {_BOX: cfg.k_box, _SPHERE: cfg.k_sphere, _CAPSULE: cfg.k_capsule}
        best_t = jnp.full((cfg.width, nb, rows), jnp.inf, jnp.float32)
        best_g = jnp.full((cfg.width, nb, rows), -1, jnp.int32)
        bound = jnp.full((cfg.width, nb), jnp.inf, jnp.float32)  # min E over overflowing selections
        for t, ids in self.type_ids.items():
            ids_j = jnp.asarray(ids)
            size = self.geom_size[ids_j]
            cc, rc = c_cam[ids_j], r_cam[ids_j]
            p_loc = -jnp.einsum("gai,ga->gi", rc, cc)  # ray origin in the geom frame
            table = jnp.concatenate([rc.reshape(-1, 9), p_loc, size], -1)  # (Gt, 15)
            if kmax[t] < len(ids):
                # the column's candidates (W, k), nearest footprint entry first, then per band
                col = self._column_candidates(cc, rc, _bounding_box_size(t, size), kmax[t])
                cand, valid, e = self._band_candidates(col)  # (W, nb, k) each, (W, nb)
                bound = jnp.minimum(bound, e)
                tab = jnp.where(valid[..., None], table[cand], 0.0)  # one gather, (W, nb, k, 15)
                cand_g = ids_j[cand]
            else:  # few geoms of this type: test them all in every column, no culling needed
                valid = jnp.ones((1, 1, len(ids)), bool)
                tab = table[None, None]  # (1, 1, Gt, 15)
                cand_g = jnp.broadcast_to(ids_j, (cfg.width, nb, len(ids)))
            comp = [tab[..., None, :, i] for i in range(15)]  # each (W | 1, nb | 1, 1, k)
            # direction in the geom frame: d_i = r[0,i] X + r[1,i] Y + r[2,i] (camera dir (X, Y, 1))
            d = [comp[0 * 3 + i] * X + comp[2 * 3 + i] + comp[1 * 3 + i] * Y for i in range(3)]
            p = comp[9:12]
            s = comp[12:15]
            if t == _BOX:
                tt = ray_box_soa(*s, *p, *d)
            elif t == _SPHERE:
                tt = ray_sphere_soa(s[0], *p, *d)
            else:
                tt = ray_capsule_soa(s[0], s[1], *p, *d)
            tt = jnp.where(valid[:, :, None, :], tt, jnp.inf)  # (W, nb, R, k)
            tt = jnp.broadcast_to(tt, (cfg.width, nb, rows, tt.shape[-1]))
            t_min, j = _min_argmin(tt)  # (W, nb, R)
            g_min = jnp.take_along_axis(cand_g, j, axis=-1)
            better = t_min < best_t
            best_t = jnp.where(better, t_min, best_t)
            best_g = jnp.where(better, g_min, best_g)

        best_t = best_t.reshape(cfg.width, nb * rows)[:, : cfg.height]  # (W, H)
        best_g = best_g.reshape(cfg.width, nb * rows)[:, : cfg.height]
        bound = jnp.repeat(bound, rows, axis=1)[:, : cfg.height]
        found = jnp.minimum(best_t, cfg.max_depth)
        uncertain = jnp.sum(found > bound).astype(jnp.int32)
        return self._finish(best_t.T, best_g.T, o, rot, xpos, xmat, uncertain)

    # ------------------------------------------------------------------ internals
    def _column_candidates(self, c_cam, r_cam, bsize, k):
        """The k geoms (of G of one type) that each column meets with the smallest footprint entry.

        Footprint of the geom's bounding box on the camera's (X, Z) plane = zonotope of the three
        projected half-axes v_i = bsize_i (r[0, i], r[2, i]) = intersection of three slabs with
        normals perpendicular to each v_i; the column is the 2D ray t (x_j tan_h, 1), so its
        parameter t is the z-depth, and [t_lo, t_hi] is where the column is inside the footprint.
        Returns a dict of f32/i32[W, k]: cand (index into the G geoms), t_lo (+inf: no real
        candidate), t_hi, y_lo / y_hi (the bounding box's vertical extent, camera Y), and e f32[W, 1]
        (the largest kept t_lo where the column met more than k geoms, else +inf).
        """
        cfg = self.config
        X = jnp.asarray(self._col_x)[:, None]  # (W, 1)
        vx = [r_cam[:, 0, i] * bsize[:, i] for i in range(3)]  # each (G,)
        vz = [r_cam[:, 2, i] * bsize[:, i] for i in range(3)]
        t_lo = jnp.zeros((), jnp.float32)  # rays start at the camera
        t_hi = jnp.full((), cfg.max_depth, jnp.float32)
        for i in range(3):
            ln = jnp.sqrt(vx[i] ** 2 + vz[i] ** 2)
            # a generator along the camera's up axis has no direction: any normal gives a valid slab
            ok = ln > 1e-9
            nx = jnp.where(ok, -vz[i] / jnp.where(ok, ln, 1.0), 1.0)
            nz = jnp.where(ok, vx[i] / jnp.where(ok, ln, 1.0), 0.0)
            width = sum(jnp.abs(nx * vx[j] + nz * vz[j]) for j in range(3))
            p = -(nx * c_cam[:, 0] + nz * c_cam[:, 2])  # ray origin (0, 0) along n
            inv = _safe_inv(nx[None] * X + nz[None])  # (W, G)
            ta = (-width - p)[None] * inv
            tb = (width - p)[None] * inv
            t_lo = jnp.maximum(t_lo, jnp.minimum(ta, tb))
            t_hi = jnp.minimum(t_hi, jnp.maximum(ta, tb))
        # vertical extent vs the column's wedge |Y| <= Z tan_v y_max (pixel centres) up to depth t_hi
        hy = sum(jnp.abs(r_cam[:, 1, i]) * bsize[:, i] for i in range(3))
        y_lo, y_hi = c_cam[:, 1] - hy, c_cam[:, 1] + hy
        ymax = self._row_y_max * t_hi
        passed = (t_hi >= t_lo) & (y_lo[None] <= ymax) & (y_hi[None] >= -ymax)
        # materialise once: left to fusion, XLA recomputes the scores in every consumer
        score = jax.lax.optimization_barrier(jnp.where(passed, t_lo, jnp.inf))
        if cfg.select == "rank":
            neg, cand, lost = _nearest_ranked(score, k)
        else:
            neg, cand = jax.lax.top_k(-score, k)  # (W, k) nearest-entry candidates
            lost = False
        # E = largest kept t_lo. A max over all k values, not neg[:, -1]: XLA:CPU maps top_k to its
        # fast TopK call only when the whole [0:k] slice is used, else it sorts all G per column
        # (measured 10x slower). A column whose selection lost candidates unordered certifies no ray.
        overflow = jnp.sum(jnp.isfinite(score), -1) > k
        e = jnp.where(overflow, jnp.max(-neg, axis=-1), jnp.inf)
        e = jnp.where(lost, -jnp.inf, e)[:, None]
        th = jnp.take_along_axis(t_hi, cand, axis=1)
        return dict(cand=cand, t_lo=-neg, t_hi=th, y_lo=y_lo[cand], y_hi=y_hi[cand], e=e)

    def _band_candidates(self, col):
        """Per (column, band), the column's candidates `col` that the band's rays may hit.

        Kept: the k_band with the smallest t_lo whose possible rows (slopes y = Y / t for Y in
        [y_lo, y_hi], t in [t_lo, t_hi]) meet the band. Returns i32[W, nb, K] candidate indices,
        bool[W, nb, K] real ones, and f32[W, nb] E (the largest kept t_lo where the column's or
        the band's selection dropped some, else +inf: a ray whose hit is at depth <= E is exact).
        """
        cfg = self.config
        tl, th, ylo, yhi = col["t_lo"], col["t_hi"], col["y_lo"], col["y_hi"]  # (W, k)
        k = tl.shape[-1]
        inv_lo = jnp.where(tl > 0, 1.0 / jnp.where(tl > 0, tl, 1.0), jnp.inf)  # t_lo = 0: unbounded
        inv_hi = 1.0 / jnp.maximum(th, 1e-9)
        y_max = jnp.where(yhi >= 0, jnp.where(yhi > 0, yhi * inv_lo, 0.0), yhi * inv_hi)
        y_min = jnp.where(ylo <= 0, jnp.where(ylo < 0, ylo * inv_lo, 0.0), ylo * inv_hi)
        tol = 1e-4
        lo, hi = jnp.asarray(self._band_lo)[:, None], jnp.asarray(self._band_hi)[:, None]
        ok = (y_max[:, None] >= lo - tol) & (y_min[:, None] <= hi + tol) & jnp.isfinite(tl)[:, None]
        cand = jnp.broadcast_to(col["cand"][:, None], ok.shape)
        e = jnp.broadcast_to(col["e"], ok.shape[:2])
        kb = min(cfg.k_band, k)
        if kb == k:  # every column candidate is tested in each band it may appear in
            return cand, ok, e
        # The column's candidates come nearest first (top_k), so the band's are its first kb with
        # ok. With c the running count of ok, the i-th of them sits at #{p : c_p <= i}: one
        # comparison count per slot, no sort and no one-hot table.
        c = jnp.cumsum(ok, axis=-1, dtype=jnp.int32)  # (W, nb, k)
        j = jnp.sum(c[..., None, :] <= jnp.arange(kb, dtype=jnp.int32)[:, None], -1, dtype=jnp.int32)
        n = c[..., -1:]  # (W, nb, 1) candidates of the band
        valid = jnp.arange(kb) < n
        kept = ok & (c <= kb)
        e_band = jnp.max(jnp.where(kept, tl[:, None], -jnp.inf), -1)
        e = jnp.minimum(e, jnp.where(n[..., 0] > kb, e_band, jnp.inf))
        j = jnp.minimum(j, k - 1)  # slots past the band's count (invalid) read the last candidate
        return jnp.take_along_axis(cand, j, axis=-1), valid, e

    def _finish(self, t, g, o, rot, xpos, xmat, uncertain) -> CameraOutput:
        """Depth / segmentation / shaded colour from per-pixel hit depth t and geom g (H, W)."""
        cfg = self.config
        hit = (g >= 0) & (t <= cfg.max_depth)
        g = jnp.where(hit, g, -1)
        gs = jnp.maximum(g, 0)
        depth = jnp.where(hit, t, cfg.max_depth).astype(jnp.float32)
        # Shading: the normal at the hit point, computed in the hit geom's frame. Components as
        # separate (H, W) arrays (see the ray kernels) and one gather of every per-geom value.
        table = jnp.concatenate([xpos, xmat.reshape(-1, 9), self.geom_size, self.geom_rgb], -1)[gs]
        col = [table[..., i] for i in range(table.shape[-1])]  # 18 x (H, W)
        c, rg, size, rgb = col[0:3], col[3:12], col[12:15], col[15:18]  # rg[3 j + i] = R[j, i]
        dirs = jnp.asarray(self._dirs_cam)  # (H, W, 3) camera directions, Z component 1
        dw = [sum(rot[j, a] * dirs[..., a] for a in range(3)) for j in range(3)]  # world directions
        tt = jnp.where(hit, t, 0.0)
        rel = [o[j] + tt * dw[j] - c[j] for j in range(3)]  # hit point - geom centre (world)
        q = tuple(sum(rg[3 * j + i] * rel[j] for j in range(3)) for i in range(3))
        n_loc = _local_normal(self.geom_type[gs], size, q)
        n = [sum(rg[3 * j + i] * n_loc[i] for i in range(3)) for j in range(3)]
        inv_len = jax.lax.rsqrt(dw[0] ** 2 + dw[1] ** 2 + dw[2] ** 2)
        towards = -sum(n[j] * dw[j] for j in range(3)) * inv_len  # headlight: n . (-dhat)
        sun = sum(n[j] * self._light[j] for j in range(3))
        lam = 0.5 * jnp.maximum(0.0, towards) + 0.5 * jnp.maximum(0.0, sun)
        shade = cfg.ambient + (1.0 - cfg.ambient) * lam
        rgb = jnp.stack([jnp.where(hit, ci * shade, 0.0) for ci in rgb], -1)
        return CameraOutput(
            depth=depth,
            rgb=rgb.astype(jnp.float32),
            instance=jnp.where(hit, self.geom_instance[gs], -1),
            semantic=jnp.where(hit, self.geom_class[gs], 0),
            geom=g,
            uncertain=jnp.asarray(uncertain, jnp.int32),
        )

    def _render_mjx(self, data: mjx.Data, pose: jax.Array) -> CameraOutput:
        cfg = self.config
        o, dirs_w = world_rays(pose, cfg)
        flat = dirs_w.reshape(-1, 3)
        excl = self.exclude_body if self.exclude_body >= 0 else -1
        dist, gid = jax.vmap(lambda v: mjx.ray(self.mjx_model, data, o, v, bodyexclude=excl))(flat)
        t = jnp.where(gid >= 0, dist, jnp.inf).reshape(cfg.height, cfg.width).astype(jnp.float32)
        g = gid.reshape(cfg.height, cfg.width).astype(jnp.int32)
        xmat = data.geom_xmat.reshape(-1, 3, 3).astype(jnp.float32)
        _, rot = camera_frame(pose, cfg)
        return self._finish(t, g, o, rot, data.geom_xpos.astype(jnp.float32), xmat, jnp.zeros((), jnp.int32))


def _min_argmin(x: jax.Array):
    """(min, argmin) over the last axis in one variadic reduction.

    jnp.min + jnp.argmin are two reductions, and XLA fuses the (expensive) kernel producing x into
    both, evaluating it twice."""
    idx = jax.lax.broadcasted_iota(jnp.int32, x.shape, x.ndim - 1)

    def pick(a, b):
        (va, ia), (vb, ib) = a, b
        take_b = (vb < va) | ((vb == va) & (ib < ia))
        return jnp.where(take_b, vb, va), jnp.where(take_b, ib, ia)

    return jax.lax.reduce(
        (x, idx), (jnp.array(jnp.inf, x.dtype), jnp.array(0, jnp.int32)), pick, (x.ndim - 1,)
    )


def _nearest_ranked(score: jax.Array, k: int):
    """`lax.top_k(-score, k)` for rows with few finite scores, without a sort.

    score f32[W, G] (+inf: not a candidate). XLA:GPU sorts every row of a top_k whose k > 16 or
    whose rows are shorter than 1024 (a house column: 311 boxes, ~9 finite). Here a cumsum packs
    each row's first C = min(G, 2k) finite scores, in index order, into C slots; each slot's rank
    is a count of the slots before it in (score, index) order (C x C comparisons), and output q
    takes the slot ranked q (C x k). Returns (-values, indices) as top_k does for every slot with
    a finite value (padding slots: +inf values, indices not top_k's), and bool[W], rows with more
    than C finite scores, whose dropped candidates need not be the farthest."""
    w, g = score.shape
    c = min(g, 2 * k)
    finite = jnp.isfinite(score)
    pos = jnp.cumsum(finite, axis=-1, dtype=jnp.int32) - 1  # slot of each finite score
    slot = jnp.where(finite & (pos < c), pos, c)  # slot c takes the rest and is dropped
    rows = jnp.arange(w)[:, None]
    ids = jnp.broadcast_to(jnp.arange(g, dtype=jnp.int32), (w, g))
    packed = jnp.full((w, c + 1), g, jnp.int32).at[rows, slot].set(ids)[:, :c]  # g: empty
    vals = jnp.where(packed < g, jnp.take_along_axis(score, jnp.minimum(packed, g - 1), -1), jnp.inf)
    order = jnp.arange(c)  # slots are in index order, so the slot breaks ties as top_k's index does
    before = (vals[:, None, :] < vals[:, :, None]) | (
        (vals[:, None, :] == vals[:, :, None]) & (order[None, :] < order[:, None])
    )
    rank = jnp.sum(before, -1, dtype=jnp.int32)  # (W, C): a permutation of 0..C-1 per row
    pick = rank[:, :, None] == jnp.arange(k, dtype=jnp.int32)  # (W, C, k): one slot per output
    idx = jnp.sum(jnp.where(pick, packed[:, :, None], 0), axis=1)
    val = jnp.min(jnp.where(pick, vals[:, :, None], jnp.inf), axis=1)
    return -val, jnp.minimum(idx, g - 1), pos[:, -1] + 1 > c


def _bounding_box_size(gtype: int, size: jax.Array) -> jax.Array:
    """Half sizes of a box (in the geom frame) containing the geom: for the column footprints."""
    if gtype == _BOX:
        return size
    if gtype == _SPHERE:
        return jnp.repeat(size[:, :1], 3, axis=1)
    return jnp.stack([size[:, 0], size[:, 0], size[:, 0] + size[:, 1]], -1)
