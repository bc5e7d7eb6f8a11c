"""Simulator: exact discrete motions in free space, walls and table corners stop the agent without
penetration or tunnelling, no velocity carries over, vmap == single runs, the collision model
(sphere on grown blockers; the older capsule), contact filtering and the auto-chosen MJX
broadphase K; the behaviour tests run on MJX's JAX implementation and on MJX-Warp. CPU; the
jitted step / init are compiled once per implementation (~1 min in all)."""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hron_jax import sim as S
from hron_jax.paths import REPO_ROOT

ROOT = REPO_ROOT
HOUSE = os.path.join(ROOT, "scenes", "house.xml")

# Floor (x, y in [-6, 6]); an axis-aligned wall whose face is at x = 3; a wall at 45 deg through
# (-3, -3); a table; a mocap apple (no contacts); all annotated as in docs/scene_format.md.
SCENE = """
<mujoco model="sim_test">
  <compiler angle="degree"/>
  <asset><material name="plain" rgba="1 1 1 1"/></asset>
  <worldbody>
    <body name="room:living_room:0">
      <geom type="box" pos="0 0 -0.025" size="6 6 0.025"/>
    </body>
    <geom name="wall:east" type="box" pos="3.05 0 1.25" size="0.05 6 1.25"/>
    <geom name="wall:diag" type="box" pos="-3 -3 1.25" size="0.05 3 1.25" euler="0 0 45"/>
    <body name="furniture:table:0" pos="0 4 0">
      <geom type="box" pos="0 0 0.725" size="0.6 0.4 0.025"/>
      <geom type="box" pos="0.55 0.35 0.35" size="0.025 0.025 0.35"/>
    </body>
    <body name="object:apple:0" mocap="true" pos="0 0 -5">
      <geom type="sphere" size="0.045" rgba="0.8 0.1 0.1 1"/>
    </body>
  </worldbody>
</mujoco>
"""
WALL_X = 3.0
R = S.SimConfig().radius
NB = 20  # one batch size for every vmapped test: one compile


@pytest.fixture(scope="module", params=["jax", "warp"])
def sim(request):
    """Every behaviour test runs on both MJX implementations (warp: MJX-Warp on Warp's CPU backend)."""
    if request.param == "warp":
        pytest.importorskip("warp", reason="Warp physics needs warp-lang (the test extra installs it)")
    return S.Simulator.from_xml(SCENE, S.SimConfig(physics=request.param))


@pytest.fixture(scope="module")
def fns(sim):
    return dict(
        init=jax.jit(sim.init),
        step=jax.jit(sim.step),
        vinit=jax.jit(jax.vmap(sim.init)),
        vstep=jax.jit(jax.vmap(sim.step)),
    )


def _pose(fns, sim, pose):
    return fns["init"](jnp.asarray(pose, jnp.float32))


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def test_free_space_actions_exact(sim, fns):
    x0, y0, yaw0 = 0.3, -0.4, 0.7
    d0 = _pose(fns, sim, [x0, y0, yaw0])
    expect = {
        S.FORWARD: (x0 + 0.2 * math.cos(yaw0), y0 + 0.2 * math.sin(yaw0), yaw0),
        S.BACKWARD: (x0 - 0.2 * math.cos(yaw0), y0 - 0.2 * math.sin(yaw0), yaw0),
        S.TURN_LEFT: (x0, y0, yaw0 + math.radians(30)),
        S.TURN_RIGHT: (x0, y0, yaw0 - math.radians(30)),
        S.STOP: (x0, y0, yaw0),
    }
    for a, (ex, ey, eyaw) in expect.items():
        d = fns["step"](d0, jnp.int32(a))
        p = np.asarray(sim.agent_pose(d), np.float64)
        assert abs(p[0] - ex) < 1e-3 and abs(p[1] - ey) < 1e-3, (S.ACTION_NAMES[a], p)
        assert abs(math.degrees(_wrap(p[2] - eyaw))) < 0.2, (S.ACTION_NAMES[a], p)
        assert np.all(np.asarray(sim.agent_velocity(d)) == 0.0)
        # the plan is exact to float precision, not merely within tolerance
        assert np.hypot(p[0] - ex, p[1] - ey) < 1e-4


def test_no_velocity_carries_over(sim, fns):
    """Forward then STOP: STOP leaves the pose unchanged; 12 left turns come back to the start."""
    d = _pose(fns, sim, [0.0, 0.0, 0.0])
    d = fns["step"](d, jnp.int32(S.FORWARD))
    p1 = np.asarray(sim.agent_pose(d))
    for _ in range(3):
        d = fns["step"](d, jnp.int32(S.STOP))
    np.testing.assert_allclose(np.asarray(sim.agent_pose(d)), p1, atol=1e-6)
    assert np.all(np.asarray(d.qvel) == 0.0)
    for _ in range(12):
        d = fns["step"](d, jnp.int32(S.TURN_LEFT))
    p = np.asarray(sim.agent_pose(d))
    np.testing.assert_allclose(p[:2], p1[:2], atol=1e-5)
    assert abs(math.degrees(_wrap(p[2] - p1[2]))) < 0.2


def test_velocity_plan_properties():
    cfg = S.SimConfig()
    u = S.velocity_plan(cfg)
    dt = cfg.env_dt / cfg.substeps
    assert u[0] == 0 and u[-1] == 0 and abs(u.sum() * dt - 1) < 1e-12
    # per-substep travel stays near the contact margin (contacts are seen before deep penetration)
    assert u.max() * dt * cfg.forward_m < cfg.contact_skin + 0.01
    # deadbeat controls reproduce the plan on the implicit velocity servo in free space
    c = S.control_profile(cfg)
    a, v, q = cfg.servo_gain, 0.0, 0.0
    for n in range(cfg.substeps):
        v = (v + a * c[n]) / (1 + a)
        q += dt * v
        assert abs(v - u[n + 1]) < 1e-9
    assert abs(q - 1.0) < 1e-12 and abs(v) < 1e-12


def test_wall_stops_agent(sim, fns):
    """Repeated FORWARD into the wall: stops with the capsule at ~radius from it, never crosses."""
    d = _pose(fns, sim, [1.03, 0.0, 0.0])
    xs = []
    for _ in range(14):
        d = fns["step"](d, jnp.int32(S.FORWARD))
        p = np.asarray(sim.agent_pose(d))
        xs.append(p[0])
        assert p[0] <= WALL_X - R + 0.01, xs  # penetration <= 1 cm at every step end
        assert abs(p[1]) < 1e-4 and abs(p[2]) < 1e-4  # head-on: no sideways drift or spin
        assert np.all(np.asarray(d.qvel) == 0.0)
    assert xs[-1] >= WALL_X - R - 0.04, xs  # it did reach the wall (within margin)
    # backing away works normally after the contact
    d = fns["step"](d, jnp.int32(S.BACKWARD))
    assert abs(float(sim.agent_pose(d)[0]) - (xs[-1] - 0.2)) < 1e-3


def test_wall_all_start_offsets(sim, fns):
    """Contact at every phase of a step (start offsets ~1 cm apart over one step's travel): the
    body capsule never ends a step more than 1 cm inside (measured worst: 0.6 mm outside)."""
    off = np.linspace(0.0, 0.2, NB, endpoint=False) + 0.0037
    starts = np.stack([WALL_X - R - 0.2 - off, np.zeros(NB), np.zeros(NB)], -1)
    d = fns["vinit"](jnp.asarray(starts, jnp.float32))
    for _ in range(3):
        d = fns["vstep"](d, jnp.full((NB,), S.FORWARD, jnp.int32))
        x = np.asarray(d.qpos[:, sim.qpos_adr[0]])
        assert np.all(x <= WALL_X - R + 0.01), x
    assert np.all(x >= WALL_X - R - 0.04), x


def test_oblique_wall_slides_never_crosses(sim, fns):
    """Driving at the 45-degree wall: the agent slides along it, its centre stays >= R - 1 cm away."""
    n = np.array([1.0, 1.0]) / math.sqrt(2)  # wall normal (the wall's local x axis)
    c = np.array([-3.0, -3.0])
    start = c + 1.0 * n
    d = _pose(fns, sim, [start[0], start[1], math.atan2(-n[1], -n[0]) + math.radians(20)])
    for _ in range(15):
        d = fns["step"](d, jnp.int32(S.FORWARD))
        p = np.asarray(sim.agent_pose(d))
        dist = (p[:2] - c) @ n - 0.05  # from the wall face to the agent's axis
        assert dist >= R - 0.01, (p, dist)
    along = (p[:2] - start) @ np.array([-n[1], n[0]])
    assert abs(along) > 0.3  # it slid along the wall instead of sticking


def test_vmap_equals_single_runs(sim, fns):
    """A batch of NB envs (random poses, some running into walls) equals NB single runs."""
    rng = np.random.default_rng(0)
    poses = np.concatenate(
        [
            np.array([[0.0, 0.0, 0.0], [2.5, 0.5, 0.1], [-1.0, 2.0, 2.0]]),
            np.stack(
                [rng.uniform(-2.5, 2.7, NB - 3), rng.uniform(-2.5, 2.5, NB - 3), rng.uniform(-3, 3, NB - 3)],
                -1,
            ),
        ]
    )
    acts = rng.integers(0, 5, size=(NB, 6))
    acts[1] = [0, 0, 0, 0, 3, 0]  # env 1 drives into the east wall
    db = fns["vinit"](jnp.asarray(poses, jnp.float32))
    for t in range(acts.shape[1]):
        db = fns["vstep"](db, jnp.asarray(acts[:, t], jnp.int32))
    for i in range(NB):
        d = _pose(fns, sim, poses[i])
        for t in range(acts.shape[1]):
            d = fns["step"](d, jnp.int32(acts[i, t]))
        np.testing.assert_allclose(np.asarray(db.qpos[i]), np.asarray(d.qpos), atol=1e-5)
        np.testing.assert_allclose(np.asarray(db.qvel[i]), np.asarray(d.qvel), atol=1e-6)


def test_state_carries_what_the_next_step_reads():
    """SimState keeps 4 of the physics model's mjx.Data fields; stepping it gives bitwise the
    trajectory of carrying the whole mjx.Data (step_data), through free motion, turns and steps
    blocked by the wall: none of the dropped fields is read by the next step. Its scene geom
    poses are native MuJoCo's kinematics of the scene model at the final pose."""
    sim = S.Simulator.from_xml(SCENE, S.SimConfig(physics="jax"))
    turns = [S.BACKWARD, S.TURN_LEFT, S.FORWARD, S.TURN_RIGHT, S.FORWARD, S.FORWARD, S.TURN_LEFT]
    actions = jnp.asarray([S.FORWARD] * 4 + turns)

    @jax.jit
    def both(pose):
        start = sim.init(pose)
        state = jax.lax.scan(lambda s, a: (sim.step(s, a), None), start, actions)[0]
        full = jax.lax.scan(lambda d, a: (sim.step_data(d, a), None), sim.data(start), actions)[0]
        return state, full

    state, full = both(jnp.asarray([WALL_X - R - 0.45, 0.3, 0.0], jnp.float32))
    assert float(state.qpos[0]) > WALL_X - R - 0.05  # the walk ended against the wall
    assert np.abs(np.asarray(full.qacc_warmstart)).max() > 0  # the solver state is not blank
    for f in S.PHYSICS_FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(state, f)), np.asarray(getattr(full, f)), err_msg=f)
    m = sim.mj_model
    d = mujoco.MjData(m)
    d.qpos[sim.qpos_adr] = np.asarray(state.qpos)
    mujoco.mj_kinematics(m, d)
    assert abs(float(state.qpos[2])) > 0.1  # the agent's geoms were turned, not only moved
    np.testing.assert_allclose(np.asarray(state.geom_xpos), d.geom_xpos, atol=2e-6)
    np.testing.assert_allclose(np.asarray(state.geom_xmat).reshape(-1, 9), d.geom_xmat, atol=2e-6)


def test_init_places_mocap_objects(sim, fns):
    pos = np.array([[1.0, 2.0, 0.8]], np.float32)
    quat = np.array([[1.0, 0.0, 0.0, 0.0]], np.float32)
    d = fns["init"](jnp.zeros(3), jnp.asarray(pos), jnp.asarray(quat))
    g = sim.mj_model.body("object:apple:0").geomadr[0]
    np.testing.assert_allclose(np.asarray(d.geom_xpos[g]), pos[0], atol=1e-6)
    p = np.asarray(sim.agent_pose(d))
    np.testing.assert_allclose(p, [0, 0, 0], atol=1e-7)


def test_table_corner_blocks_like_a_wall(sim, fns):
    """Driving past the table top's corner (a slab at 0.70-0.75 m) with the agent's centre 1 cm
    outside the slab's side: it stops at ~R from the corner. MJX's capsule-box collider lost exactly
    this contact (test_sim_native.py), which the sphere-on-prisms collision model avoids."""
    corner = np.array([0.6, 3.6])
    d = _pose(fns, sim, [corner[0] + 0.01, corner[1] - R - 0.35, math.pi / 2])
    for _ in range(4):
        d = fns["step"](d, jnp.int32(S.FORWARD))
        p = np.asarray(sim.agent_pose(d))
        assert np.linalg.norm(p[:2] - corner) >= R - 0.01, p
    assert np.linalg.norm(p[:2] - corner) < R + 0.04, p  # it reached the corner


def test_physics_model_blockers_span_the_agent(sim):
    """The physics model is the agent (two bodies: world and agent) and the blockers as world geoms
    at their world poses; it grows the table (slab and leg) to prisms over the agent's height about
    their centres; walls (already taller) and the model the camera sees keep their sizes."""
    m, mp = sim.mj_model, sim.physics_model
    assert mp.nbody == 2 and mp.nmocap == 0 and mp.nq == m.nq == 3
    assert mp.ngeom == len(sim.blockers) + len(sim.agent_geoms)
    table = list(range(m.body("furniture:table:0").geomadr[0], m.body("furniture:table:0").geomadr[0] + 2))
    assert sorted(sim.grown_blockers) == table
    d, dp = mujoco.MjData(m), mujoco.MjData(mp)
    mujoco.mj_kinematics(m, d)
    mujoco.mj_kinematics(mp, dp)
    np.testing.assert_allclose(dp.geom_xpos[sim.physics_blockers], d.geom_xpos[sim.blockers], atol=1e-9)
    np.testing.assert_allclose(dp.geom_xmat[sim.physics_blockers], d.geom_xmat[sim.blockers], atol=1e-7)
    physics = dict(zip(sim.blockers, sim.physics_blockers))
    cfg = sim.config
    for g in table:
        assert d.geom_xpos[g, 2] - mp.geom_size[physics[g], 2] < cfg.bottom_clearance - cfg.contact_skin
        assert d.geom_xpos[g, 2] + mp.geom_size[physics[g], 2] > cfg.height + cfg.contact_skin
    np.testing.assert_array_equal(m.geom_size[table, 2], [0.025, 0.35])
    same = [g for g in sim.blockers if g not in table]
    np.testing.assert_array_equal(mp.geom_size[[physics[g] for g in same]], m.geom_size[same])
    assert m.geom("wall:east").id in same


def test_contact_filter(sim):
    m = sim.physics_model
    agent_geom = sim.collider_geom
    assert list(np.nonzero(m.geom_contype)[0]) == [agent_geom] == [m.geom(S.AGENT_COLLIDER).id]
    assert m.geom_type[agent_geom] == mujoco.mjtGeom.mjGEOM_SPHERE
    assert list(np.nonzero(m.geom_conaffinity)[0]) == list(sim.physics_blockers)
    ms = sim.mj_model  # the same filter, which the geodesic map reads
    assert list(np.nonzero(ms.geom_contype)[0]) == [ms.geom(S.AGENT_COLLIDER).id]
    assert list(np.nonzero(ms.geom_conaffinity)[0]) == list(sim.blockers)
    floor = ms.body("room:living_room:0").geomadr[0]
    apple = ms.body("object:apple:0").geomadr[0]
    assert floor not in sim.blockers and apple not in sim.blockers
    walls = [ms.geom("wall:east").id, ms.geom("wall:diag").id]
    assert set(walls) <= set(sim.blockers)
    # MJX sees exactly agent x blockers as candidate pairs; the broadphase keeps K of them
    from mujoco.mjx._src import collision_driver

    pairs = list(collision_driver.geom_pairs(m))
    assert len(pairs) == len(sim.blockers)
    assert all(agent_geom in p[:2] for p in pairs)
    assert 1 <= sim.max_geom_pairs <= len(sim.blockers)
    assert m.numeric_data[m.numeric("max_geom_pairs").adr[0]] == sim.max_geom_pairs


def test_capsule_collider_is_the_model_before_spheres():
    """collider='capsule' (runs before 2026-12-02): one agent geom, the capsule grown by the skin,
    colliding against the scene's own boxes (none grown)."""
    sim = S.Simulator.from_xml(SCENE, S.SimConfig(physics="jax", collider="capsule"))
    m = sim.physics_model
    assert len(sim.grown_blockers) == 0
    np.testing.assert_array_equal(m.geom_size[sim.physics_blockers], sim.mj_model.geom_size[sim.blockers])
    assert len(sim.agent_geoms) == 1 and [sim.collider_geom] == [m.geom(S.AGENT_GEOM).id]
    assert m.geom_type[sim.collider_geom] == mujoco.mjtGeom.mjGEOM_CAPSULE
    assert m.geom_size[sim.collider_geom, 0] == pytest.approx(R + sim.config.contact_skin)
    assert list(np.nonzero(m.geom_contype)[0]) == [sim.collider_geom]
    with pytest.raises(ValueError, match="unknown collider 'box'"):
        S.Simulator.from_xml(SCENE, S.SimConfig(collider="box"))


@pytest.mark.skipif(not os.path.exists(HOUSE), reason="scenes/house.xml not present")
def test_auto_max_geom_pairs_keeps_every_contact():
    """Native MuJoCo (all pairs, no broadphase cap) vs MJX's top-K by bounding-sphere distance:
    at random agent positions across the house, every blocker in contact ranks within K."""
    sim = S.Simulator.from_file(HOUSE)
    m = sim.physics_model
    assert sim.max_geom_pairs < len(sim.blockers) // 4  # culling actually removes pairs
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    agent_geom, blockers = sim.collider_geom, sim.physics_blockers
    lo = d.geom_xpos[blockers, :2].min(0)
    hi = d.geom_xpos[blockers, :2].max(0)
    rng = np.random.default_rng(0)
    touching = 0
    for _ in range(3000):
        d.qpos[sim.qpos_adr] = [*rng.uniform(lo, hi), 0.0]
        mujoco.mj_fwdPosition(m, d)
        geoms = {int(g) for c in d.contact[: d.ncon] for g in (c.geom1, c.geom2)} - {agent_geom}
        if not geoms:
            continue
        touching += 1
        metric = (
            np.linalg.norm(d.geom_xpos[blockers] - d.geom_xpos[agent_geom], axis=1)
            - m.geom_rbound[blockers]
            - m.geom_rbound[agent_geom]
        )
        for g in geoms:
            mg = metric[list(blockers).index(g)]
            assert (metric <= mg).sum() <= sim.max_geom_pairs, (g, d.qpos[sim.qpos_adr])
    assert touching > 100


@pytest.mark.parametrize(
    "change, message",
    [
        (
            (
                '<geom type="box" pos="0.55 0.35 0.35" size="0.025 0.025 0.35"/>',
                '<geom type="mesh" mesh="tetra" pos="0.55 0.35 0.35"/>',
            ),
            "blocks the agent but is a mjGEOM_MESH; blockers must be boxes, capsules, spheres",
        ),
        (
            (
                '<body name="furniture:table:0" pos="0 4 0">',
                '<body name="furniture:table:0" pos="0 4 0"><joint type="hinge" axis="0 0 1"/>',
            ),
            "the scene has 1 joint coordinates; scene bodies must be static or mocap",
        ),
    ],
)
def test_scenes_the_physics_model_cannot_take_are_named(change, message):
    """A blocker the physics model cannot rebuild from its sizes (a mesh) or a scene body with a
    joint: a one-line ValueError that says what is wrong, not a wrong simulation."""
    mesh = '<mesh name="tetra" vertex="0 0 0  0.1 0 0  0 0.1 0  0 0 0.7"/></asset>'
    with pytest.raises(ValueError, match=message):
        S.Simulator.from_xml(SCENE.replace(*change).replace("</asset>", mesh), S.SimConfig(physics="jax"))
