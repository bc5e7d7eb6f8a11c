"""Tests of hron_jax.metric_map: cells of a known box from a real camera frame, highest point wins,
accumulation, egocentric crop orientation, global view, pre-mapping; and of the model's map branch
(models.encoders.MapEncoder) on its observations: channel layout, class embedding, rgbd_mm end to
end on NavigationEnv observations.

The box scene is written here: a 6 m x 6 m floor centred at the origin (so the grid origin is
(-3, -3)), one cabinet box whose footprint covers exactly the cells [15, 19) x [11, 15) with 8 cm
of floor left inside the border cells, and a bowl in the object pool. A camera 2 m up looking
straight down (pitch -90 deg) sees the box top and the floor around it densely enough that every
cell gets points.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hron_jax.metric_map import MapConfig, MetricMap
from hron_jax.paths import REPO_ROOT
from hron_jax.scenes import load_scene
from hron_jax.scenes import vocabulary as V
from hron_jax.sensors import Camera, CameraConfig, world_rays

ROOT = REPO_ROOT
SYMMETRIC = os.path.join(ROOT, "scenes", "symmetric_room.xml")

C = 0.23
NC = V.NUM_CLASSES
I0, I1, J0, J1 = 15, 19, 11, 15  # the box's cells (x rows, y columns)
MARGIN = 0.08  # floor left inside the border cells
BOX_TOP = 0.5
X0, X1 = -3 + C * I0 + MARGIN, -3 + C * I1 - MARGIN
Y0, Y1 = -3 + C * J0 + MARGIN, -3 + C * J1 - MARGIN
BOWL_XY = (-1.0, 0.5)

BOX_XML = f"""
<mujoco model="box_map">
  <asset><material name="plain" rgba="1 1 1 1"/></asset>
  <worldbody>
    <body name="room:kitchen:0"><geom type="box" pos="0 0 -0.025" size="3 3 0.025"/></body>
    <body name="furniture:cabinet:0" pos="{(X0 + X1) / 2} {(Y0 + Y1) / 2} 0">
      <geom type="box" pos="0 0 {BOX_TOP / 2}" size="{(X1 - X0) / 2} {(Y1 - Y0) / 2} {BOX_TOP / 2}"/>
    </body>
    <body name="object:bowl:0" mocap="true" pos="0 0 -5">
      <geom type="box" size="0.08 0.08 0.035" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""

DOWN = CameraConfig(width=64, height=64, vfov_deg=90.0, mount_height=2.0, pitch_deg=-90.0)
ROOM_CLS = V.class_id("room", "kitchen")
BOX_CLS = V.class_id("furniture", "cabinet")
BOWL_CLS = V.class_id("object", "bowl")


def height(key):
    return np.where(np.asarray(key) >= 0, np.asarray(key) // NC, -1)


def cls(key):
    return np.where(np.asarray(key) >= 0, np.asarray(key) % NC, -1)


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    path = tmp_path_factory.mktemp("scenes") / "box_map.xml"
    path.write_text(BOX_XML)
    scene = load_scene(str(path))
    m = scene.model
    cam = Camera(m, DOWN, scene.geom_instance, scene.geom_class)
    render = jax.jit(cam.render_geoms)

    def frame(pose, bowl=False):
        d = mujoco.MjData(m)
        if bowl:
            d.mocap_pos[0] = (*BOWL_XY, 0.035)
        mujoco.mj_forward(m, d)
        out = render(
            jnp.asarray(d.geom_xpos, jnp.float32),
            jnp.asarray(d.geom_xmat, jnp.float32),
            jnp.asarray(pose, jnp.float32),
        )
        return out

    mm = MetricMap(scene, DOWN, MapConfig())
    return dict(scene=scene, mm=mm, frame=frame, update=jax.jit(mm.update))


def test_grid_layout(box):
    mm = box["mm"]
    np.testing.assert_allclose(mm.origin, [-3.0, -3.0])
    assert mm.shape == (27, 27)  # ceil(6 / 0.23)
    assert (mm.reset() == -1).all()


def test_known_box_fills_exactly_its_cells(box):
    mm, pose = box["mm"], (0.0, 0.0, 0.0)
    f = box["frame"](pose)
    key = np.asarray(box["update"](mm.reset(), jnp.asarray(pose), f.depth, f.semantic))
    want = np.zeros(mm.shape, bool)
    want[I0:I1, J0:J1] = True
    c, h = cls(key), height(key)
    np.testing.assert_array_equal(c == BOX_CLS, want)
    assert (h[want] == round(BOX_TOP * 1000)).all()
    seen = key >= 0
    assert (c[seen & ~want] == ROOM_CLS).all() and (h[seen & ~want] == 0).all()
    # The camera sees a 4 m x 4 m patch of floor around the agent: all those cells are observed up
    # to the box (behind it, in +x, the box hides part of the floor); nothing beyond the patch.
    assert seen[5:I1, 5:22].all() and not seen[:3].any() and not seen[24:].any()

    # Highest wins within one frame: the border cell I0 also received floor points (the 8 cm strip
    # between the cell edge and the box, on the camera's side) and still holds the box top.
    o, dirs = world_rays(jnp.asarray(pose, jnp.float32), DOWN)
    pts = np.asarray(o + f.depth[..., None] * dirs)
    cell = np.floor((pts[..., :2] - mm.origin) / C).astype(int)
    floor_in_border = (
        (np.asarray(f.semantic) == ROOM_CLS)
        & (cell[..., 0] == I0)
        & (cell[..., 1] >= J0)
        & (cell[..., 1] < J1)
    )
    assert floor_in_border.sum() > 0
    assert (c[I0, J0:J1] == BOX_CLS).all()


def test_accumulation_over_frames_and_never_lower(box):
    mm, update, frame = box["mm"], box["update"], box["frame"]
    pa, pb = (-1.5, -1.0, 0.0), (1.5, 1.2, 2.0)
    fa, fb = frame(pa), frame(pb)
    ka = update(mm.reset(), jnp.asarray(pa), fa.depth, fa.semantic)
    kb = update(mm.reset(), jnp.asarray(pb), fb.depth, fb.semantic)
    kab = update(ka, jnp.asarray(pb), fb.depth, fb.semantic)
    np.testing.assert_array_equal(kab, np.maximum(ka, kb))
    sa, sb, sab = (np.asarray(k) >= 0 for k in (ka, kb, kab))
    assert sab.sum() > max(sa.sum(), sb.sum()) and (sab == (sa | sb)).all()

    # The bowl appears where the floor was seen, and the map keeps it after the bowl is gone.
    p = (-1.0, -0.5, 0.0)
    bi, bj = (int((BOWL_XY[0] + 3) / C), int((BOWL_XY[1] + 3) / C))
    k1 = update(mm.reset(), jnp.asarray(p), frame(p).depth, frame(p).semantic)
    assert cls(k1)[bi, bj] == ROOM_CLS and height(k1)[bi, bj] == 0
    f2 = frame(p, bowl=True)
    k2 = update(k1, jnp.asarray(p), f2.depth, f2.semantic)
    assert cls(k2)[bi, bj] == BOWL_CLS and height(k2)[bi, bj] == 70
    k3 = update(k2, jnp.asarray(p), frame(p).depth, frame(p).semantic)
    np.testing.assert_array_equal(k3, k2)


def test_egocentric_crop_orientation(box):
    """A marker 1.2 m ahead of the agent lands in the top rows, centre columns; one 1.2 m to its
    left in the left columns, centre rows; for several headings."""
    mm = box["mm"]
    m = mm.config.crop
    observe = jax.jit(mm.observe)
    agent = np.array([-0.3, 0.2])
    for yaw in (0.0, 1.0, 2.5, -2.0):
        fwd, left = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        for where, xy in (("ahead", agent + 1.2 * fwd), ("left", agent + 1.2 * left)):
            key = np.full(mm.shape, -1, np.int32)
            i, j = np.floor((xy - mm.origin) / C).astype(int)
            key[i - 1 : i + 2, j - 1 : j + 2] = 300 * NC + BOX_CLS  # a 3 x 3 blob survives resampling
            obs = np.asarray(observe(jnp.asarray(key), jnp.asarray([*agent, yaw], jnp.float32)))
            assert obs.shape == (m, m, 3)
            rows, cols = np.nonzero(obs[..., 2] == BOX_CLS)
            assert len(rows) >= 4
            np.testing.assert_allclose(obs[rows, cols, 1], 0.3 / mm.config.max_height, atol=1e-6)
            along = m / 2 - 0.5 - 1.2 / C  # crop index 1.2 m from the centre
            r, c = rows.mean(), cols.mean()
            if where == "ahead":
                assert abs(r - along) < 1.0 and abs(c - (m / 2 - 0.5)) < 1.0, (yaw, r, c)
            else:
                assert abs(c - along) < 1.0 and abs(r - (m / 2 - 0.5)) < 1.0, (yaw, r, c)

    # With a real frame: the box (at +x) is ahead when facing +x and on the right facing +y.
    f = box["frame"]((0.0, 0.0, 0.0))
    key = box["update"](mm.reset(), jnp.asarray([0.0, 0.0, 0.0]), f.depth, f.semantic)
    for yaw, side in ((0.0, "ahead"), (np.pi / 2, "right")):
        obs = np.asarray(observe(key, jnp.asarray([0.0, 0.0, yaw], jnp.float32)))
        rows, cols = np.nonzero(obs[..., 2] == BOX_CLS)
        assert len(rows) == (I1 - I0) * (J1 - J0)  # cell-aligned at 0 and 90 deg
        if side == "ahead":
            assert rows.max() < m / 2 and abs(cols.mean() - (m / 2 - 0.5)) < 1.0
        else:
            assert cols.min() >= m / 2 and abs(rows.mean() - (m / 2 - 0.5)) < 1.0
        assert (obs[rows, cols, 1] == np.float32(0.5 / 2.5)).all() and (obs[rows, cols, 0] == 1).all()
    assert (obs[..., 0] == 0).sum() > 0 and (obs[obs[..., 0] == 0] == 0).all()


def test_global_view(box):
    scene = box["scene"]
    mm = MetricMap(scene, DOWN, MapConfig(egocentric=False))
    f = box["frame"]((0.0, 0.0, 0.0))
    key = mm.update(mm.reset(), jnp.asarray([0.0, 0.0, 0.0]), f.depth, f.semantic)
    pose = jnp.asarray([0.5, -1.0, 2.0], jnp.float32)
    obs = np.asarray(mm.observe(key, pose))
    assert obs.shape == mm.shape + (5,)
    np.testing.assert_array_equal(obs[..., 2], np.maximum(cls(key), 0))
    np.testing.assert_array_equal(obs[..., 0], np.asarray(key) >= 0)
    i, j = int((0.5 + 3) / C), int((-1.0 + 3) / C)
    marked = np.nonzero(np.abs(obs[..., 3:]).sum(-1))
    assert list(zip(*marked)) == [(i, j)]
    np.testing.assert_allclose(obs[i, j, 3:], [np.cos(2.0), np.sin(2.0)], atol=1e-6)


def test_premap_contents():
    scene = load_scene(SYMMETRIC)
    cam = CameraConfig(width=32, height=32)
    mm = MetricMap(scene, cam, MapConfig(), premap=True)
    key = np.asarray(mm.reset())
    assert key.shape == mm.shape
    c, h = cls(key), height(key)
    centres = (
        mm.origin
        + (np.stack(np.meshgrid(np.arange(mm.shape[0]), np.arange(mm.shape[1]), indexing="ij"), -1) + 0.5) * C
    )
    assert (key >= 0).all()  # floor and walls cover the bounds
    # Never a pool object (the target included); every category of the file's furniture is there.
    assert not np.isin(c, [V.class_id("object", o) for o in V.OBJECTS]).any()
    assert {V.class_id("furniture", "table"), V.class_id("furniture", "shelf")} <= set(c.ravel().tolist())
    # The table tops: every cell whose centre lies over a top holds the table at the top's height.
    for t in ("furniture:table:0", "furniture:table:1"):
        n = scene.index_of(t)
        lo, hi = scene.aabb_center[n] - scene.aabb_half[n], scene.aabb_center[n] + scene.aabb_half[n]
        over = np.all((centres > lo[:2]) & (centres < hi[:2]), -1)
        assert over.sum() >= 10
        assert (c[over] == V.class_id("furniture", "table")).all()
        assert (h[over] == round(hi[2] * 1000)).all()
    # The 0.1 m walls are in every cell they cross (one sample per cell centre would miss most).
    wall = np.zeros(mm.shape, bool)
    structure = np.nonzero(scene.geom_instance < 0)[0]
    for g in structure:
        lo = scene.geom_aabb_center[g, :2] - scene.geom_aabb_half[g, :2]
        hi = scene.geom_aabb_center[g, :2] + scene.geom_aabb_half[g, :2]
        i0, j0 = np.floor((lo - mm.origin) / C).astype(int)
        i1, j1 = np.ceil((hi - mm.origin) / C).astype(int)
        wall[i0:i1, j0:j1] = True
    assert (c[wall] == V.STRUCTURE_CLASS).all() and (h[wall] == 2500).all()
    # Open floor far from everything: the room at height 0.
    assert c[mm.shape[0] // 2, mm.shape[1] // 2 - 4] == V.class_id("room", "living_room")
    assert h[mm.shape[0] // 2, mm.shape[1] // 2 - 4] == 0

    # What the camera sees is never above the premap (it holds the highest surface of each cell),
    # and an apple placed on a table rises above it there.
    cam = CameraConfig(width=64, height=64)
    mm = MetricMap(scene, cam, MapConfig(), premap=True)
    render = Camera(scene.model, cam, scene.geom_instance, scene.geom_class).render_geoms
    d = mujoco.MjData(scene.model)
    apple = scene.index_of("object:apple:0")
    k = scene.slot_names.index("furniture:table:0:onTop:0")
    top = scene.slot_center[k, 2] - scene.slot_half[k, 2]  # the table's top surface
    apple_xyz = (scene.slot_center[k, 0] + 0.3, scene.slot_center[k, 1], top + 0.045)
    d.mocap_pos[scene.mocap_id[apple]] = apple_xyz
    mujoco.mj_forward(scene.model, d)
    pose = jnp.asarray([-1.9, -1.0, np.pi / 2], jnp.float32)
    f = jax.jit(render)(jnp.asarray(d.geom_xpos, jnp.float32), jnp.asarray(d.geom_xmat, jnp.float32), pose)
    seen = np.asarray(mm.update(jnp.full(mm.shape, -1, jnp.int32), pose, f.depth, f.semantic))
    obj = cls(seen) == V.class_id("object", "apple")
    ai, aj = np.floor((np.asarray(apple_xyz[:2]) - mm.origin) / C).astype(int)
    assert obj.any() and np.abs(np.argwhere(obj) - [ai, aj]).max() <= 1
    assert (height(seen)[obj] > h[obj]).all() and (height(seen)[obj] <= round((top + 0.09) * 1000)).all()
    assert (height(seen)[~obj] <= h[~obj] + 1).all()
    both = np.asarray(mm.update(mm.reset(), pose, f.depth, f.semantic))
    np.testing.assert_array_equal(both[obj], seen[obj])
    np.testing.assert_array_equal(both[~obj], key[~obj])


# --- the model's map branch (models.encoders.MapEncoder) on this module's observations ----------
SMALL_CONV = dict(features=(4, 4, 4), kernels=(4, 3, 3), strides=(2, 2, 1), fc=(8, 8, 8))


def _map_encoder(class_features=3):
    from hron_jax.models.encoders import MapEncoder

    return MapEncoder(NC, class_features, **SMALL_CONV)


def _random_params(module, x, seed=0):
    """Variables of `module` for input `x`: normals, std sqrt(2 / fan-in) for kernels and tables,
    0.1 for biases (nonzero, so no layer is exactly linear or dead by construction)."""
    shapes = jax.eval_shape(module.init, jax.random.PRNGKey(0), x)
    r = np.random.default_rng(seed)

    def fill(s):
        std = np.sqrt(2.0 / np.prod(s.shape[:-1])) if len(s.shape) >= 2 else 0.1
        return jnp.asarray(r.standard_normal(s.shape) * std, s.dtype)

    return jax.tree.map(fill, shapes)


def _key_with_blocks(shape, blocks):
    """Key grid with each (i0, i1, j0, j1, height_mm, class) block filled, -1 elsewhere."""
    key = np.full(shape, -1, np.int32)
    for i0, i1, j0, j1, h, c in blocks:
        key[i0:i1, j0:j1] = h * NC + c
    return key


BLOCKS = [
    (2, 6, 3, 9, 0, ROOM_CLS),
    (8, 12, 5, 8, 500, BOX_CLS),
    (14, 16, 14, 20, 70, BOWL_CLS),
    (20, 23, 1, 4, 2500, V.STRUCTURE_CLASS),
]


def test_map_encoder_reads_observe_channel_layout(box):
    """The encoder's first conv sees exactly [observed, height, (heading), embed(class) if observed],
    each built here from the key (not from observe's channels): the encoder's reading of the
    channels is the layout observe writes, in the global and the egocentric view."""
    from hron_jax import metric_map
    from hron_jax.models import encoders

    assert encoders.MAP_OBSERVED_CHANNEL == metric_map.OBSERVED_CHANNEL
    assert encoders.MAP_CLASS_CHANNEL == metric_map.CLASS_CHANNEL
    scene = box["scene"]
    mm_g = MetricMap(scene, DOWN, MapConfig(egocentric=False))
    key = _key_with_blocks(mm_g.shape, BLOCKS)
    pose = np.array([0.4, -0.7, 0.9], np.float32)
    enc = _map_encoder()

    def expected(params, k, extra):
        seen = k >= 0
        table = np.asarray(params["params"]["class_embed"]["embedding"])
        feats = [
            seen[..., None].astype(np.float32),
            (np.where(seen, k // NC, 0) / 1000.0 / 2.5)[..., None].astype(np.float32),
            *extra,
            np.where(seen[..., None], table[np.where(seen, k % NC, 0)], 0.0).astype(np.float32),
        ]
        x = np.concatenate(feats, -1)
        return encoders.ConvEncoder(**SMALL_CONV).apply({"params": params["params"]["conv"]}, x)

    # Global view: cell (i, j) of the observation is cell (i, j) of the key; heading in 3-4.
    obs_g = mm_g.observe(jnp.asarray(key), jnp.asarray(pose))
    params = _random_params(enc, obs_g)
    heading = np.asarray(obs_g[..., 3:])
    np.testing.assert_allclose(enc.apply(params, obs_g), expected(params, key, [heading]), atol=1e-4)

    # Egocentric view at yaw 0 with the agent on a cell corner: crop cell (r, c) is grid cell
    # (K + M/2 - 1 - r, L + M/2 - 1 - c) (rows ahead = +x, columns left = +y), -1 off the grid.
    m = 24
    mm_e = MetricMap(scene, DOWN, MapConfig(crop=m))
    K, L = 12, 9
    pose = np.array([-3 + K * C, -3 + L * C, 0.0], np.float32)
    obs_e = mm_e.observe(jnp.asarray(key), jnp.asarray(pose))
    assert obs_e.shape == (m, m, 3)
    gi, gj = np.meshgrid(K + m // 2 - 1 - np.arange(m), L + m // 2 - 1 - np.arange(m), indexing="ij")
    inside = (gi >= 0) & (gi < mm_e.shape[0]) & (gj >= 0) & (gj < mm_e.shape[1])
    k_e = np.where(inside, key[np.clip(gi, 0, mm_e.shape[0] - 1), np.clip(gj, 0, mm_e.shape[1] - 1)], -1)
    assert (k_e >= 0).sum() > 20 and len(np.unique(k_e[k_e >= 0] % NC)) == 4
    params = _random_params(enc, obs_e, seed=1)
    np.testing.assert_allclose(enc.apply(params, obs_e), expected(params, k_e, []), atol=1e-4)


def test_map_encoder_class_is_categorical(box):
    """The class reaches the output only through its embedding row, never as a number:
    relabelling the classes by any permutation, with the table's rows permuted alike, leaves the
    output unchanged (a scalar class channel cannot do that: its first layer is affine in the id),
    while relabelling the map alone changes it; two classes whose rows are equal are
    indistinguishable; an all-zero table makes the output independent of the class channel; the
    class of an unobserved cell is never read."""
    mm = MetricMap(box["scene"], DOWN, MapConfig(egocentric=False))
    key = _key_with_blocks(mm.shape, BLOCKS)
    obs = np.asarray(mm.observe(jnp.asarray(key), jnp.asarray([0.0, 0.0, 0.0], jnp.float32)))
    enc = _map_encoder()
    params = _random_params(enc, obs)
    apply = jax.jit(enc.apply)
    out = np.asarray(apply(params, obs))
    table = params["params"]["class_embed"]["embedding"]

    def relabel(o, perm):
        o = o.copy()
        o[..., 2] = perm[o[..., 2].astype(int)]
        return o

    def with_table(t):
        return {"params": {**params["params"], "class_embed": {"embedding": t}}}

    perm = np.random.default_rng(3).permutation(NC)
    inv = np.argsort(perm)
    same = np.asarray(apply(with_table(table[inv]), relabel(obs, perm)))  # row perm[c] = old row c
    np.testing.assert_allclose(same, out, atol=1e-5)
    assert np.abs(np.asarray(apply(params, relabel(obs, perm))) - out).max() > 1e-3

    # Classes 3 and 17 on the bowl's and the box's cells: equal rows -> equal outputs; the swap of
    # two ids is no "larger" or "smaller" change than any other.
    a, b = 3, 17
    swap = np.arange(NC)
    swap[[BOWL_CLS, BOX_CLS]] = [a, b]
    o1 = relabel(obs, swap)
    swap[[BOWL_CLS, BOX_CLS]] = [b, a]
    o2 = relabel(obs, swap)
    tied = table.at[b].set(table[a])
    np.testing.assert_allclose(apply(with_table(tied), o1), apply(with_table(tied), o2), atol=1e-6)
    assert np.abs(np.asarray(apply(params, o1)) - np.asarray(apply(params, o2))).max() > 1e-3

    zero = with_table(jnp.zeros_like(table))
    shuffled = obs.copy()
    shuffled[..., 2] = np.random.default_rng(4).integers(0, NC, obs.shape[:2])
    np.testing.assert_allclose(apply(zero, shuffled), apply(zero, obs), atol=1e-6)

    unseen = obs[..., 0] == 0
    garbage = obs.copy()
    garbage[..., 2] = np.where(unseen, 7.0, obs[..., 2])
    np.testing.assert_array_equal(apply(params, garbage), out)


def test_rgbd_mm_on_navigation_env_observations():
    """End to end: the rgbd_mm model on NavigationEnv observations (metric_map, premap so the map
    holds many classes): forward on a batch of two resets, finite gradients, and the class table
    gets gradient exactly on the rows of the classes seen in the maps."""
    from hron_jax.envs import make_env
    from hron_jax.models import ModelConfig, make_model

    env = make_env("exploratory", image_size=8, metric_map=True, premap=True, max_steps=20)
    reset = jax.jit(env.reset)
    states = [reset(jax.random.PRNGKey(s)) for s in (0, 1)]
    obs = jax.tree.map(lambda *a: jnp.stack(a), *[s.obs for s in states])
    m = env.config.map.crop
    assert obs["map"].shape == (2, m, m, 3)
    seen_classes = np.unique(np.asarray(obs["map"])[..., 2][np.asarray(obs["map"])[..., 0] > 0])
    assert len(seen_classes) >= 3 and (seen_classes > V.NOTHING_CLASS).all()

    cfg = ModelConfig(
        conv_features=(4, 4, 4),
        conv_kernels=(8, 4, 3),
        conv_strides=(4, 2, 1),
        cnn_fc=(16, 16, 16),
        goal_fc=(16, 16, 16),
        fusion_fc=(16, 16, 16),
        head_fc=(16, 16),
    )
    model = make_model("rgbd_mm", env.num_actions, cfg)
    # Random variables of the model's structure (flax init compiles one QR per weight shape).
    variables = _random_params(model, jax.tree.map(lambda a: a[0], obs))

    @jax.jit
    def run(v, o):
        def loss(p):
            logits, value = model.apply(p, o)
            return jnp.sum(jax.nn.log_softmax(logits)[:, 0]) + jnp.sum(value**2), (logits, value)

        return jax.grad(loss, has_aux=True)(v)

    grads, (logits, value) = run(variables, obs)
    assert logits.shape == (2, env.num_actions) and value.shape == (2,)
    assert np.isfinite(np.asarray(logits)).all() and np.isfinite(np.asarray(value)).all()
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(grads))
    g_table = np.asarray(grads["params"]["core"]["map_encoder"]["class_embed"]["embedding"])
    has_grad = np.abs(g_table).max(-1) > 0
    np.testing.assert_array_equal(np.nonzero(has_grad)[0], seen_classes.astype(int))
