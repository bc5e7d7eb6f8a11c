"""Both MJX implementations against native MuJoCo (`mj_step` on the physics model with the same
controls, every geom pair, MuJoCo's own colliders) on house.xml: every step of random walks that
run into walls and furniture agrees to well under a millimetre, for MJX's JAX implementation and
for MJX-Warp (on Warp's CPU backend here); vmap, nested vmap and single Warp calls give the same
worlds; the env runs on Warp under jit, vmap and scan. Also documents the MJX capsule-box collider
defect that made the agent collide as a sphere against prisms (hron_jax/sim.py, _physics_model).
First Warp run on a machine: ~20 s of Warp kernel compiles (cached in ~/.cache/warp)."""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from hron_jax import sim as S
from hron_jax.paths import REPO_ROOT

HOUSE = os.path.join(REPO_ROOT, "scenes", "house.xml")
WALKERS, STEPS = 24, 20
# A pose from which FORWARD grazes the corner of the bed (box 8.25..9.25 x 0.13..2.13) and its leg:
# native MuJoCo stops the agent after 3 mm.
BED_CORNER = (8.02, 2.155, -0.109)
needs_warp = pytest.mark.skipif(not S.warp_installed(), reason="needs warp-lang (the test extra has it)")


@pytest.fixture(scope="module")
def sims():
    impls = ("jax", "warp") if S.warp_installed() else ("jax",)
    return {p: S.Simulator.from_file(HOUSE, S.SimConfig(physics=p)) for p in impls}


def _native_step(sim, d, pose, action):
    m = sim.physics_model
    mujoco.mj_resetData(m, d)
    d.qpos[sim.qpos_adr] = pose
    delta = np.asarray(sim.action_delta(jnp.asarray(pose, jnp.float32), action), np.float64)
    for c in np.asarray(sim._ctrl_profile, np.float64):
        d.ctrl[:] = delta * c
        mujoco.mj_step(m, d)
    p = d.qpos[sim.qpos_adr].copy()
    p[2] = (p[2] + math.pi) % (2 * math.pi) - math.pi
    return p


@pytest.fixture(scope="module")
def native_walks(sims):
    """(start pose, action, native end pose) of every step of WALKERS native random walks from
    collision-free starts spread over the house (forward-heavy, so they meet walls and furniture)."""
    sim = sims["jax"]
    m, d = sim.physics_model, mujoco.MjData(sim.physics_model)
    ms, ds = sim.mj_model, mujoco.MjData(sim.mj_model)  # the scene, where its floors are
    rng = np.random.default_rng(0)
    mujoco.mj_kinematics(ms, ds)
    roots = ms.body_rootid[ms.geom_bodyid]
    floors = [g for g in range(sim.scene_ngeom) if ms.body(roots[g]).name.startswith("room:")]
    starts = []
    while len(starts) < WALKERS:
        g = floors[rng.integers(len(floors))]
        half = np.abs(ds.geom_xmat[g].reshape(3, 3)) @ ms.geom_size[g]
        xy = ds.geom_xpos[g, :2] + rng.uniform(-1, 1, 2) * np.maximum(half[:2] - sim.config.radius, 0)
        pose = np.array([*xy, rng.uniform(-math.pi, math.pi)])
        mujoco.mj_resetData(m, d)
        d.qpos[sim.qpos_adr] = pose
        mujoco.mj_forward(m, d)
        if d.ncon == 0 and abs(_native_step(sim, d, pose, S.FORWARD)[0] - pose[0]) < 1.0:
            starts.append(pose)
    rows = [(np.array(BED_CORNER), S.FORWARD)]
    for pose in starts:
        for _ in range(STEPS):
            rows.append((pose, int(rng.choice(4, p=[0.55, 0.15, 0.15, 0.15]))))
            pose = _native_step(sim, d, pose, rows[-1][1])
    poses = np.array([r[0] for r in rows], np.float32)
    actions = np.array([r[1] for r in rows], np.int32)
    ends = np.array([_native_step(sim, d, p, a) for p, a in zip(poses, actions)])
    return poses, actions, ends


def _steps(sim, poses, actions):
    f = jax.jit(jax.vmap(lambda p, a: sim.agent_pose(sim.step(sim.init(p), a))))
    return np.asarray(f(jnp.asarray(poses), jnp.asarray(actions)))


def _xy_error(a, b):
    return np.abs(a[:, :2] - b[:, :2]).max(1)


@pytest.mark.parametrize("physics", ["jax", pytest.param("warp", marks=needs_warp)])
def test_steps_match_native_mujoco(sims, native_walks, physics):
    poses, actions, native = native_walks
    ends = _steps(sims[physics], poses, actions)
    moved = np.linalg.norm(native[:, :2] - poses[:, :2], axis=1)
    blocked = (actions < 2) & (moved < 0.19)
    assert blocked.sum() >= 0.05 * len(poses), "the walks must exercise contacts"
    err = _xy_error(ends, native)
    assert err.max() < 5e-4, f"worst xy error {err.max():.2e} m at step {err.argmax()}"
    yaw = np.abs((ends[:, 2] - native[:, 2] + math.pi) % (2 * math.pi) - math.pi)
    assert yaw.max() < 1e-4
    assert abs(native[0, 0] - BED_CORNER[0]) < 0.01  # the bed corner blocks the agent


# A vertical capsule (radius 0.22) 0.201 m from a tall box's vertical edge, its axis 2 cm outside
# the plane of the nearest face: 1.9 cm of penetration, which native MuJoCo reports.
_CAPSULE_AT_EDGE = """
<mujoco>
  <worldbody>
    <geom name="box" type="box" size="0.5 1 1" pos="0 0 1" contype="0" conaffinity="1"/>
    <body pos="-0.7 1.02 0.6">
      <freejoint/>
      <geom name="capsule" type="capsule" size="0.22 0.4" contype="1" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""


def _capsule_at_edge():
    m = mujoco.MjModel.from_xml_string(_CAPSULE_AT_EDGE)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d


def test_native_capsule_box_edge_contact():
    """The reference for the xfail below: native MuJoCo reports the 1.9 cm penetration."""
    _, d = _capsule_at_edge()
    assert d.ncon > 0 and d.contact.dist[: d.ncon].min() < -0.018


@pytest.mark.xfail(strict=True, reason="MJX's JAX capsule-box collider drops contacts near box edges")
def test_mjx_capsule_box_edge_contact():
    """Why the agent does not collide as a capsule (sim._physics_model): here MJX keeps the vertical
    edge, finds its direction within 8 deg of the face normal, prefers the face contact, and the
    face's side planes clip it away. Fails loudly (strict) once a MuJoCo release fixes it."""
    m, d = _capsule_at_edge()
    dx = jax.jit(mjx.forward)(mjx.put_model(m), mjx.put_data(m, d))
    assert float(np.asarray(dx._impl.contact.dist).min()) < -0.018


@needs_warp
def test_warp_batching_single_and_nested_agree(sims, native_walks):
    sim = sims["warp"]
    poses, actions, _ = native_walks
    poses, actions = jnp.asarray(poses[:12]), jnp.asarray(actions[:12])
    one = lambda p, a: sim.agent_pose(sim.step(sim.init(p), a))
    flat = np.asarray(jax.jit(jax.vmap(one))(poses, actions))
    nested = np.asarray(jax.jit(jax.vmap(jax.vmap(one)))(poses.reshape(3, 4, 3), actions.reshape(3, 4)))
    single = np.asarray(jax.jit(one)(poses[5], actions[5]))
    np.testing.assert_array_equal(nested.reshape(12, 3), flat)
    np.testing.assert_array_equal(single, flat[5])


@needs_warp
def test_resolve_physics():
    assert S.resolve_physics("jax") == "jax"
    assert S.resolve_physics("warp") == "warp"
    if jax.default_backend() == "cpu":
        assert S.resolve_physics("auto") == "jax"
    with pytest.raises(ValueError, match="unknown physics 'mjx'"):
        S.resolve_physics("mjx")


@needs_warp
def test_navigation_env_runs_on_warp_physics():
    """The exploratory env with Warp physics: vmapped steps with in-step auto-resets inside a scan,
    the same observations' shapes as with JAX physics, and the agent moves."""
    from hron_jax.envs import make_env

    env = make_env("exploratory", image_size=8, max_steps=6, sim=S.SimConfig(physics="warp"))
    assert env.sim.physics == "warp"
    n = 4
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), n))
    start = np.asarray(jax.vmap(env.agent_pose)(state))

    def body(s, a):
        s = jax.vmap(env.step)(s, a)
        return s, (jax.vmap(env.agent_pose)(s), s.done)

    acts = jnp.zeros((8, n), jnp.int32)  # FORWARD
    state, (poses, done) = jax.jit(lambda s: jax.lax.scan(body, s, acts))(state)
    poses, done = np.asarray(poses), np.asarray(done)
    assert done[5].all() and not done[:5].any()  # max_steps 6: every env reset in-step once
    travelled = np.linalg.norm(poses[4, :, :2] - start[:, :2], axis=1)
    assert (travelled > 0.05).all() and (travelled <= 5 * 0.2 + 1e-4).all()
    for leaf in jax.tree.leaves(state.obs):
        assert np.isfinite(np.asarray(leaf, np.float32)).all()
