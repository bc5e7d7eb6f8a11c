"""Tests for hron_jax.geodesic: rasterisation, distance fields, lookups, oracle.

Every scene is a 6 m x 6 m floor (box, top at z = 0) plus a few obstacles, rasterised at h = 0.1 m
with supersample 3, so all grids are 60 x 60 and the solver compiles once. Ground truths are
closed forms (circle wraps, wall ends) or an exact visibility-graph shortest path over the rounded
(Minkowski-inflated) rectangles.
"""

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from hron_jax import geodesic as geo

R = 0.2  # agent radius
H = 0.1  # cell size
EPS = geo.stencil_error_bound(48)  # 0.75 %: worst open-space overestimate of the default stencil


def _box(x0, y0, x1, y1, z0=0.0, z1=1.0, yaw_deg=0.0, extra=""):
    return (
        f'<geom type="box" size="{(x1 - x0) / 2} {(y1 - y0) / 2} {(z1 - z0) / 2}" '
        f'pos="{(x0 + x1) / 2} {(y0 + y1) / 2} {(z0 + z1) / 2}" '
        f'euler="0 0 {yaw_deg}" {extra}/>'
    )


def _model(geoms="", bodies=""):
    xml = (
        f'<mujoco><asset><material name="m"/></asset><worldbody>'
        f'<geom name="floor" type="box" size="3 3 0.05" pos="0 0 -0.05"/>{geoms}{bodies}'
        f'</worldbody></mujoco>'
    )
    return mujoco.MjModel.from_xml_string(xml)


def _grid(geoms="", bodies="", radius=R, **kw):
    return geo.occupancy_grid(
        _model(geoms, bodies), config=geo.GridConfig(cell_size=H, agent_radius=radius, **kw)
    )


def _point_field(grid, xy):
    """Field to a point source: cells within 1.5 h of xy start at their straight-line distance.
    Tests put sources on cell centres: then the field is the stencil metric from that centre,
    <= (1 + EPS) x Euclidean in open space, with no seed-rounding term."""
    d = np.linalg.norm(np.asarray(grid.centres()) - np.asarray(xy), axis=-1)
    init = np.where(d < 1.5 * H, d, np.inf).astype(np.float32)
    return geo.grid_distance_fields(grid, init[None])[0]


# --- exact shortest paths among rounded rectangles (visibility graph) ----------------------------


def _rect(cx, cy, hx, hy, yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([cx, cy]) + np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]) @ np.array(
        [[c, s], [-s, c]]
    )


def _seg_poly_dist(a, b, poly):
    """Distance from segments a[N, 2]-b[N, 2] to a filled convex CCW polygon: f64[N]."""
    e0, e1 = poly, np.roll(poly, -1, 0)

    def pt_seg(p, u, v):
        uv = v - u
        t = np.clip(((p - u) * uv).sum(-1) / np.maximum((uv * uv).sum(-1), 1e-18), 0, 1)
        return np.linalg.norm(p - u - t[..., None] * uv, axis=-1)

    A, B, U, V = a[:, None], b[:, None], e0[None], e1[None]
    d = np.minimum.reduce([pt_seg(A, U, V), pt_seg(B, U, V), pt_seg(U, A, B), pt_seg(V, A, B)])

    def cross(o, p, q):
        return (p[..., 0] - o[..., 0]) * (q[..., 1] - o[..., 1]) - (p[..., 1] - o[..., 1]) * (
            q[..., 0] - o[..., 0]
        )

    crossing = (cross(U, V, A) * cross(U, V, B) < 0) & (cross(A, B, U) * cross(A, B, V) < 0)
    d = np.where(crossing, 0.0, d).min(1)
    inside = (cross(e0[None], e1[None], a[:, None]) >= 0).all(1)
    return np.where(inside, 0.0, d)


def _exact_path(a, b, rects, r=R, arc_deg=5.0, tol=2e-3):
    """Shortest path length a -> b avoiding polygons inflated by r: nodes are a, b and points on
    each corner's rounding arc (r + 1e-5 out), edges the pairs whose segment keeps clearance."""
    nodes = [np.asarray(a, float), np.asarray(b, float)]
    for poly in rects:
        for k in range(4):
            n_in = poly[k] - poly[k - 1]
            n_out = poly[(k + 1) % 4] - poly[k]
            a0 = math.atan2(-n_in[0], n_in[1])  # outward normal of the incoming edge (CCW)
            a1 = math.atan2(-n_out[0], n_out[1])
            span = (a1 - a0) % (2 * math.pi)
            for t in np.linspace(0, span, int(math.ceil(math.degrees(span) / arc_deg)) + 1):
                nodes.append(poly[k] + (r + 1e-5) * np.array([math.cos(a0 + t), math.sin(a0 + t)]))
    p = np.array(nodes)
    keep = np.ones(len(p), bool)
    for poly in rects:
        keep &= _seg_poly_dist(p, p, poly) >= r - tol
    p = p[keep | (np.arange(len(p)) < 2)]
    i, j = np.triu_indices(len(p), 1)
    ok = np.ones(len(i), bool)
    for poly in rects:
        ok &= _seg_poly_dist(p[i], p[j], poly) >= r - tol
    w = np.linalg.norm(p[i] - p[j], axis=1)
    m = csr_matrix((np.r_[w[ok], w[ok]], (np.r_[i[ok], j[ok]], np.r_[j[ok], i[ok]])), shape=(len(p), len(p)))
    return dijkstra(m, indices=0)[1]


# --- rasterisation -------------------------------------------------------------------------------


def test_rasterisation_matches_analytic_footprints():
    yaw = math.radians(30)
    tilt = math.radians(40)
    geoms = (
        # yaw-rotated box: footprint an oriented rectangle
        '<geom type="box" size="0.6 0.15 0.5" pos="-1.5 1.5 0.5" euler="0 0 30"/>'
        # box tilted about x: footprint the axis-aligned rectangle of its projection
        '<geom type="box" size="0.3 0.2 0.3" pos="1.5 1.5 0.6" euler="40 0 0"/>'
        # horizontal capsule: footprint a stadium
        '<geom type="capsule" fromto="-2 -1.5 0.3 -0.8 -0.8 0.3" size="0.1"/>'
        # vertical capsule and sphere: discs
        '<geom type="capsule" size="0.15 0.4" pos="1.5 -1.5 0.6"/>'
        '<geom type="sphere" size="0.25" pos="0.2 -1.8 0.5"/>'
    )
    grid = _grid(geoms)
    assert grid.shape == (60, 60) and grid.supersample == 3
    fine = np.asarray(grid.fine)
    hf = H / 3
    ii, jj = np.meshgrid(np.arange(fine.shape[0]), np.arange(fine.shape[1]), indexing="ij")
    p = np.stack([-3 + (jj + 0.5) * hf, -3 + (ii + 0.5) * hf], -1)

    def rect_dist(q, centre, half, ang):
        c, s = math.cos(ang), math.sin(ang)
        d = q - centre
        local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
        return np.linalg.norm(np.maximum(np.abs(local) - half, 0), axis=-1)

    def seg_dist(q, a, b):
        a, b = np.asarray(a), np.asarray(b)
        t = np.clip(((q - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
        return np.linalg.norm(q - a - t[..., None] * (b - a), axis=-1)

    dists = [
        rect_dist(p, (-1.5, 1.5), (0.6, 0.15), yaw),
        rect_dist(p, (1.5, 1.5), (0.3, 0.2 * math.cos(tilt) + 0.3 * math.sin(tilt)), 0.0),
        seg_dist(p, (-2, -1.5), (-0.8, -0.8)) - 0.1,
        np.linalg.norm(p - (1.5, -1.5), axis=-1) - 0.15,
        np.linalg.norm(p - (0.2, -1.8), axis=-1) - 0.25,
    ]
    d = np.min(dists, 0)
    expect = d >= R
    sure = np.abs(d - R) > 1e-6  # cells exactly on the inflated boundary may round either way
    assert (fine == expect)[sure].all()
    assert (~fine).sum() > 1000  # the obstacles are really there
    np.testing.assert_array_equal(np.asarray(grid.free), fine[1::3, 1::3])


def test_obstacle_filters():
    geoms = (
        _box(-2.5, -2.5, -2.0, -2.0, 1.5, 1.7)  # above the agent (height 1.2): not an obstacle
        + _box(-1.0, -2.5, -0.5, -2.0, extra='contype="0" conaffinity="0"')  # visual only
        + _box(0.5, -2.5, 1.0, -2.0, extra='contype="2" conaffinity="2"')  # other bits
        + _box(2.0, 2.0, 2.5, 2.5, 0.0, 0.1)
    )  # low step: an obstacle
    bodies = (
        '<body name="object:apple:0" mocap="true" pos="0 0 0.5">'
        '<geom type="sphere" size="0.3"/></body>'
        '<body name="cart" pos="-2 2 0.5"><joint type="slide" axis="1 0 0"/>'
        '<geom type="box" size="0.3 0.3 0.3"/></body>'
    )
    grid = _grid(geoms, bodies)
    c = np.asarray(grid.centres())

    def blocked_by(centre):  # cells within R of a 0.5 m square footprint centred at `centre`
        return np.linalg.norm(np.maximum(np.abs(c - centre) - 0.25, 0), axis=-1) < R

    # only the low step blocks: floor, high box, visual box, other bits, mocap and jointed
    # bodies do not
    np.testing.assert_array_equal(~np.asarray(grid.free), blocked_by((2.25, 2.25)))
    # with the agent on collision bit 2 the "other bits" box is an obstacle and the rest are not
    grid2 = _grid(geoms, bodies, agent_contype=2, agent_conaffinity=2)
    np.testing.assert_array_equal(~np.asarray(grid2.free), blocked_by((0.75, -2.25)))


def test_unsupported_geom_raises():
    with pytest.raises(ValueError, match="ellipsoid|ELLIPSOID"):
        _grid('<geom type="ellipsoid" size="0.2 0.3 0.4" pos="0 0 0.5"/>')


def test_world_cell_round_trip():
    grid = _grid()
    xy = jnp.array([[-2.96, 2.93], [0.0, 0.0], [1.234, -0.5]])
    rc = grid.world_to_cell(xy)
    assert np.all(np.abs(np.asarray(grid.cell_to_world(rc)) - np.asarray(xy)) <= H / 2 + 1e-6)
    np.testing.assert_array_equal(np.asarray(grid.world_to_cell(grid.cell_to_world(rc))), rc)
    assert not bool(grid.is_free(jnp.array([3.5, 0.0])))  # outside the grid


# --- distance fields -----------------------------------------------------------------------------


def test_free_space_is_euclidean_within_stencil_bound():
    grid = _grid()
    src = np.array([0.25, -0.45])  # a cell centre
    f = np.asarray(_point_field(grid, src))
    e = np.linalg.norm(np.asarray(grid.centres()) - src, axis=-1)
    # never shorter than the straight line, longer by at most the stencil's angular error
    assert (f >= e - 1e-5).all()
    assert (f <= (1 + EPS) * e + 1e-5).all()
    assert (f / np.maximum(e, 1e-9))[e > 1].max() > 1 + 0.9 * EPS  # and the bound is tight
    # continuous queries: min over visible cells k within 2 cells of field(k) + |xy - k|; the
    # best k lies <= h / 2 off the ray at <= 2.5 h, which adds < 0.01 m
    rng = np.random.default_rng(0)
    for xy in rng.uniform(-2.9, 2.9, (20, 2)):
        d = float(geo.geodesic_distance(f, grid, xy))
        ex = np.linalg.norm(xy - src)
        assert ex - 1e-4 <= d <= (1 + EPS) * ex + 0.01


def _circle_wrap(a, b, c, rad):
    """Shortest path a -> b around a disc (c, rad): tangent + arc + tangent (or straight)."""
    a, b, c = map(np.asarray, (a, b, c))
    da, db = np.linalg.norm(a - c), np.linalg.norm(b - c)
    ab = b - a
    t = np.clip((c - a) @ ab / (ab @ ab), 0, 1)
    if np.linalg.norm(a + t * ab - c) >= rad:
        return float(np.linalg.norm(ab))
    theta = math.acos(np.clip((a - c) @ (b - c) / (da * db), -1, 1))
    arc = theta - math.acos(rad / da) - math.acos(rad / db)
    return math.sqrt(da**2 - rad**2) + math.sqrt(db**2 - rad**2) + rad * arc


def test_detour_around_sphere_matches_closed_form():
    grid = _grid('<geom type="sphere" size="0.5" pos="0 0 0.5"/>')
    a, b = (-2.0, 0.1), (1.95, -0.25)  # b on a cell centre
    exact = _circle_wrap(a, b, (0, 0), 0.5 + R)
    d = float(geo.geodesic_distance(_point_field(grid, b), grid, a))
    # grid paths are collision-free continuous paths: never shorter (fine raster: 0.7 h / 3);
    # longer by the stencil bound plus at most ~h for lattice vertices around one wrap (<= 180 deg)
    assert exact - 0.025 <= d <= (1 + EPS) * exact + H, (d, exact)


def test_detour_around_wall_end_matches_hand_computed():
    # thin wall x in [-0.05, 0.05], y in [-3, 0.5]; A and B on either side below its end.
    # Inflated end = two discs (radius R) at the corners C1 = (-0.05, 0.5), C2 = (0.05, 0.5);
    # the path is tangent A->C1 disc, arc over its top, 0.1 m across, arc, tangent to B.
    grid = _grid(_box(-0.05, -3.0, 0.05, 0.5, 0.0, 2.0))
    a, b = np.array([-0.95, -0.95]), np.array([0.95, -0.95])  # on cell centres
    c1 = np.array([-0.05, 0.5])
    dist = np.linalg.norm(a - c1)
    tangent = math.sqrt(dist**2 - R**2)
    ang = math.atan2(*(a - c1)[::-1])  # direction C1 -> A
    touch = ang - math.acos(R / dist)  # the tangent point on the side facing the wall's end
    wrap = (touch - math.pi / 2) % (2 * math.pi)  # arc from the tangent point to the top
    exact = 2 * (tangent + R * wrap) + 0.1
    assert abs(exact - _exact_path(a, b, [_rect(0, -1.25, 0.05, 1.75, 0)])) < 5e-3
    d = float(geo.geodesic_distance(_point_field(grid, b), grid, a))
    assert exact - 0.025 <= d <= (1 + EPS) * exact + H, (d, exact)  # one 180-deg wrap in total


def test_rotated_obstacles_match_visibility_graph():
    rects = [
        (-1.0, 0.5, 0.9, 0.1, math.radians(25)),
        (1.0, -0.6, 0.5, 0.3, math.radians(-60)),
        (0.2, 1.9, 0.8, 0.1, 0.0),
    ]
    geoms = "".join(
        f'<geom type="box" size="{hx} {hy} 0.6" pos="{x} {y} 0.6" euler="0 0 {math.degrees(t)}"/>'
        for x, y, hx, hy, t in rects
    )
    grid = _grid(geoms)
    polys = [_rect(*r) for r in rects]
    b = (0.05, 0.15)
    f = _point_field(grid, b)
    for a in [(-2.2, 2.6), (-1.5, -1.5), (2.5, -2.0), (2.4, 2.5)]:
        exact = _exact_path(a, b, polys)
        d = float(geo.geodesic_distance(f, grid, a))
        assert exact - 0.025 <= d <= (1 + EPS) * exact + H, (a, d, exact)


def test_closed_room_is_unreachable():
    walls = _box(-1, -1, 1, -0.9) + _box(-1, 0.9, 1, 1) + _box(-1, -0.9, -0.9, 0.9) + _box(0.9, -0.9, 1, 0.9)
    grid = _grid(walls)
    f = geo.target_fields(grid, jnp.array([[0.0, 0.0]]), 0.3)[0]
    assert np.isfinite(float(geo.geodesic_distance(f, grid, (0.5, 0.5))))
    assert float(geo.geodesic_distance(f, grid, (2.5, 2.5))) == np.inf
    fa = np.asarray(f)
    outside = np.max(np.abs(np.asarray(grid.centres())), -1) > 1.3
    assert np.isinf(fa[outside]).all()
    assert np.isinf(fa[~np.asarray(grid.free)]).all()  # blocked cells are never finite
    direction, ok = geo.descent_direction(f, grid, jnp.array([2.5, 2.5]))
    assert not bool(ok) and np.all(np.asarray(direction) == 0)


@pytest.mark.parametrize("gap,passes", [(0.35, False), (0.55, True)])
def test_gap_narrower_than_agent_is_closed(gap, passes):
    # a wall across the whole floor at y = 0 with one gap centred at x = 0.3. A gap passes when it
    # is wider than 2 R; on the lattice it must be wider than 2 R + h to be sure to hold a free
    # cell centre (0.55 m: centres x = 0.25, 0.35 keep 0.225 m from the jambs).
    x0, x1 = 0.3 - gap / 2, 0.3 + gap / 2
    grid = _grid(_box(-3, -0.05, x0, 0.05) + _box(x1, -0.05, 3, 0.05))
    f = _point_field(grid, (0.35, 1.45))
    d = float(geo.geodesic_distance(f, grid, (0.35, -1.45)))
    if passes:  # straight through along the free column x = 0.35
        assert d == pytest.approx(2.9, abs=1e-4)
    else:
        assert d == np.inf


# --- batches, vmap, jit --------------------------------------------------------------------------


def test_target_fields_batch_and_vmap():
    grid = _grid(_box(-0.05, -3.0, 0.05, 0.5, 0.0, 2.0))
    targets = jnp.array([[-1.5, -1.0], [1.5, -2.0], [2.0, 2.0]])
    batch = np.asarray(geo.target_fields(grid, targets, 1.0))
    assert batch.shape == (3, 60, 60)
    inits = jax.vmap(lambda t: geo.success_init(grid, t, 1.0))(targets)
    single = jax.vmap(lambda s: geo.distance_field(grid.free, s, H, fine=grid.fine))(inits)
    np.testing.assert_allclose(batch, np.asarray(single), rtol=1e-5, atol=1e-5)
    c = np.asarray(grid.centres())
    for k, t in enumerate(np.asarray(targets)):
        inside = (np.linalg.norm(c - t, axis=-1) <= 1.0) & np.asarray(grid.free)
        assert (batch[k][inside] == 0).all()
    # open-space continuous query: distance to the disc = |p - t| - 1
    p = np.array([2.5, -0.5])
    d = float(jax.jit(geo.geodesic_distance)(jnp.asarray(batch[2]), grid, p))
    ex = np.linalg.norm(p - np.asarray(targets[2])) - 1.0
    assert ex - 1e-3 <= d <= ex * (1 + EPS) + 0.01
    # batched queries into the bank by target index == per-field queries
    xy = jnp.array([[2.5, -0.5], [-2.0, 2.0], [1.0, 1.0], [-2.9, -2.9]])
    idx = jnp.array([2, 0, 1, 1])
    banked = jax.jit(jax.vmap(lambda q, k: geo.geodesic_distance(batch, grid, q, index=k)))(xy, idx)
    for q, k, v in zip(xy, idx, np.asarray(banked)):
        assert v == pytest.approx(float(geo.geodesic_distance(batch[int(k)], grid, q)), rel=1e-6)


def test_success_band_does_not_leak_through_a_wall():
    # target 0.85 m above a wall across the floor (door far away at x in [2, 3]): the success disk
    # pokes into the inflated wall but no free success cell lies below it. Cells just below the
    # inflated wall are within 1 m + 1.5 h of the target, yet their only way in is via the door.
    grid = _grid(_box(-3, -0.05, 2.0, 0.05))  # the doorway is x in [2, 3]
    f = geo.target_fields(grid, jnp.array([[-1.0, 0.85]]), 1.0)[0]
    below = float(geo.geodesic_distance(f, grid, (-1.0, -0.3)))
    # to the door's inflated jamb (2.2, 0) 3.2 m, then >= |(2.2, 0) - target| - 1 = 2.3 m
    assert below > 5.4, below  # (a leaked band cell would give ~0.1)
    above = float(geo.geodesic_distance(f, grid, (-1.0, 2.0)))
    assert above == pytest.approx(1.15 - 1.0, abs=0.01)  # straight to the disk


def test_bool_sources_and_cell_units():
    free = np.ones((20, 30), bool)
    free[5:15, 10] = False
    src = np.zeros_like(free)
    src[10, 5] = True
    f = np.asarray(geo.distance_field(free, src, 1.0, stencil=8))
    assert f[10, 5] == 0 and f[10, 8] == pytest.approx(3.0)
    assert f[10, 6 + 1] == pytest.approx(2.0)
    assert np.isinf(f[~free]).all()
    # around the wall end (row 15 is free): must detour, longer than the straight 10 cells
    assert f[10, 15] > 10.0 + 1.0


# --- oracle --------------------------------------------------------------------------------------


def test_oracle_reaches_goal_with_good_spl():
    walls = _box(-3.0, -0.05, 1.0, 0.05, 0.0, 2.0) + _box(-0.8, 1.2, 0.8, 1.6, 0.0, 0.8)
    start, target = jnp.array([-2.0, -2.0]), jnp.array([-2.0, 2.2])
    world = _grid(walls)  # collisions at the true radius
    oracle = _grid(walls, radius=R + 0.1)  # the oracle keeps 0.1 m of clearance
    f_world = geo.target_fields(world, target[None], 1.0)[0]
    bank = geo.target_fields(oracle, jnp.stack([target, -target]), 1.0)  # the oracle's fields
    d0 = float(geo.geodesic_distance(f_world, world, start))
    turn = math.pi / 6

    def step(state, _):
        xy, yaw, travelled, done = state
        act = geo.oracle_action(bank, oracle, xy, yaw, index=0)
        nxt = xy + 0.2 * jnp.array([jnp.cos(yaw), jnp.sin(yaw)])
        along = xy + jnp.linspace(0.0, 1.0, 9)[:, None] * (nxt - xy)
        fwd = (act == geo.ORACLE_FORWARD) & jnp.all(world.los_grid().is_free(along)) & ~done
        xy2 = jnp.where(fwd, nxt, xy)
        yaw2 = yaw + jnp.where(
            done, 0.0, jnp.where(act == geo.ORACLE_LEFT, turn, jnp.where(act == geo.ORACLE_RIGHT, -turn, 0.0))
        )
        done2 = done | (jnp.linalg.norm(xy2 - target) < 1.0)
        return (xy2, yaw2, travelled + jnp.where(fwd, 0.2, 0.0), done2), act

    (xy, _, travelled, done), acts = jax.lax.scan(
        step, (start, jnp.float32(0.0), jnp.float32(0.0), jnp.array(False)), None, length=200
    )
    assert bool(done), xy
    spl = d0 / max(d0, float(travelled))
    assert spl > 0.85, (spl, d0, float(travelled))
