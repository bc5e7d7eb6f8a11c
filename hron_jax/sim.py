"""Simulator: one scene file + the agent -> one `mjx.Model`; batched, jittable physics steps.

Role
----
Compiles an annotated scene (docs/scene_format.md) together with the navigating agent into two
MuJoCo models, and steps one of them with MJX: the scene model (`mj_model`: the scene as it is plus
the agent; the camera, placement and geodesic map read it) and the physics model (`physics_model`:
the agent and the geoms that block it, nothing else; `_physics_model`). The API is functional
(Brax / MuJoCo Playground style): a `Simulator` holds only static things (models, index tables,
config) and its methods are pure functions of a state pytree, so they jit and vmap:

    sim = Simulator.from_file("scenes/house.xml")            # or from_xml / from_spec
    s = sim.init(pose, mocap_pos, mocap_quat)                  # SimState; pose f32[3] = (x, y, yaw)
    s = sim.step(s, action)                                    # action i32[] in 0..4, 0.1 s of sim
    xy_yaw = sim.agent_pose(s)                                 # f32[3], yaw wrapped to [-pi, pi)
    d = sim.data(s)                                            # the physics model's mjx.Data
    batched: jax.vmap(sim.init)(poses[B,3], mpos[B,nmocap,3], mquat[B,nmocap,4]); jax.vmap(sim.step)

The state (`SimState`) is what persists from one env step to the next: of the physics model's
mjx.Data the time, qpos, qvel and the solver's warm start (every other field is an output of the
next step's forward pass, or an input this project never sets, so `step` starts from the model's
blank mjx.Data with these set and gives bitwise the trajectory of carrying the whole mjx.Data:
tested), and the scene model's geom poses, which the sensors read (`init` runs the scene's
kinematics once, with the episode's mocap object poses; after that only the agent moves, and
`step` moves its geoms with it). Envs carry it through their loops and checkpoints.

Actions (the paper's discrete navigation actions, executed physically): FORWARD 0 (+0.2 m along the
heading), BACKWARD 1 (-0.2 m), TURN_LEFT 2 (+30 deg yaw), TURN_RIGHT 3 (-30 deg), STOP 4 (zero
velocity). One env step = `config.env_dt` = 0.1 s of simulated time (500 steps = 50 s) made of
`config.substeps` MJX steps inside one `lax.scan`.

The agent
---------
Body `agent` with slide joints `agent:x`, `agent:y` (world axes, they come first) and hinge
`agent:yaw`, so qpos[agent] = (x, y, yaw). Its body is a vertical capsule `agent:capsule` of radius
0.2 m from `bottom_clearance` (0.05 m, so floor seams and door thresholds never block it) to 1.2 m,
which is what it looks like and never collides. What collides is `agent:collider`, a sphere of the
body's radius plus `contact_skin` at mid-height, against the physics model's blockers, every
blocker box grown about its centre until it spans the agent's height (`_physics_model`): a
cylinder against prisms, i.e. planar collision for a planar motion, and a pair MJX's sphere-box
collider gets exactly right (its capsule-box collider drops contacts near box edges; see
`_physics_model`). The blockers are every scene geom that is not a room floor, not a mocap object,
and reaches into the agent's height range (walls, furniture); in the physics model they are
geoms of the world body at their world poses (conaffinity=1), and the collider is the only geom
with contype=1. Native references must step `physics_model` too. Static-static pairs never exist,
so the candidate pairs are exactly agent x blockers. MJX evaluates
every candidate pair every substep (its CPU cost scales with pairs), so the model carries the MJX
numeric `max_geom_pairs` = K: per substep MJX keeps the K pairs of smallest bounding-sphere distance
(lax.top_k). K is chosen at build time (`_auto_max_geom_pairs`) so that, for agent positions on a
5 cm grid over the whole scene, every blocker whose AABB could touch the collider ranks within the
top K: culling never drops a live contact. `SimConfig.collider='capsule'` is the collision model of
runs before 2026-12-02 (config.json files without the field load as it): no sphere, the capsule
(radius plus skin) collides against the true boxes, and MJX's JAX physics then misses contacts near
box edges (docs/benchmarks.md, Physics).

Control scheme: deadbeat velocity plan on implicit velocity servos
------------------------------------------------------------------
Each of x, y, yaw has a `velocity` actuator (force = kv (ctrl - qvel)) and the integrator is
`implicitfast`, which treats kv implicitly: per substep v' = (v + a ctrl) / (1 + a) with
a = dt kv / m exactly (m the dof's mass or inertia). An action becomes a displacement delta (world
dx, dy from the heading at the start of the step, or dyaw) and a planned velocity sequence
u_0 = 0, u_1..u_{N-1} = delta * trapezoid / (dt * sum), u_N = 0 (sum_n dt u_n = delta). The controls
c_n = ((1 + a) u_{n+1} - u_n) / a make v follow the plan exactly in free space, so the agent moves
0.2 m / turns 30 deg to float precision and ends the step at rest, independent of mass and gains.
Why this and not a position servo: a position servo must be stiff to settle 0.2 m within 0.1 s
(omega ~ 80 /s), and when a wall blocks it that stiffness times the remaining distance pushes the
capsule deep into the (soft) contact; here the push against a wall is only kv * (planned velocity),
and a small a (0.5) keeps it low (a = 1 already lets the capsule sink 14 mm; measured).
Contacts: the collider is the body radius plus a 2 cm skin (`contact_skin`), because MJX's
colliders report only penetrating contacts (they ignore geom margins: measured, dist = 1 for
separated pairs), so the early-contact zone must be part of the shape. The trapezoid caps travel
at 2.9 cm per substep, about the skin, so the body (radius 0.2) is never inside a wall at the end of
a step (worst 0.01 mm over contact at every phase of a step, MJX and native alike) and cannot
tunnel (walls are far thicker than one substep's travel). Contacts are frictionless (condim 1):
turning in contact is not resisted and the agent slides along walls it meets obliquely. When
blocked, the skin and the controller's last deceleration substep (a small pull-back) leave the body
resting 2.8-3.1 cm from the wall surface. Finally a brake zeroes the agent's qvel after
the last substep (in free space it is zero already; it matters in contact), so no velocity ever
carries into the next step: each action is a self-contained motion primitive, as in the paper.

Physics implementation (`SimConfig.physics`): 'jax' steps with MJX's JAX implementation; 'warp'
with MJX-Warp (`hron_jax.sim_warp`: vmapped envs are stepped in one call and only time, qpos and
qvel come back, so the state's solver warm start stays that of `init`); 'auto'
is warp on an NVIDIA GPU with warp-lang installed, else jax. Both agree with native MuJoCo on the
physics model to well under a millimetre (tests/test_sim_native.py).

Shapes: pose f32[3]; mocap_pos f32[nmocap, 3]; mocap_quat f32[nmocap, 4] (w, x, y, z); action i32[].
After `step`, `s.qpos`/`s.qvel` are final and `s.geom_xpos`/`geom_xmat` (f32[ngeom, 3], f32[ngeom, 3, 3]
of mj_model's geoms) are exact for the final pose. Mocap poses are constant within an episode.
"""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

FORWARD, BACKWARD, TURN_LEFT, TURN_RIGHT, STOP = 0, 1, 2, 3, 4
NUM_ACTIONS = 5
ACTION_NAMES = ("forward", "backward", "turn_left", "turn_right", "stop")

AGENT_BODY = "agent"
AGENT_GEOM = "agent:capsule"  # the agent's body as seen (no contacts)
AGENT_COLLIDER = "agent:collider"  # what collides (see _add_agent)
AGENT_JOINTS = ("agent:x", "agent:y", "agent:yaw")


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static simulator settings (hashable; changing one recompiles)."""

    radius: float = 0.2  # capsule radius (m)
    height: float = 1.2  # capsule top above the floor (m)
    bottom_clearance: float = 0.05  # capsule bottom above the floor (m): thresholds / seams don't block
    mass: float = 20.0  # kg; the yaw inertia is that of a solid cylinder, m r^2 / 2
    env_dt: float = 0.1  # simulated seconds per env step (paper: 500 steps = 50 s)
    substeps: int = 10  # MJX steps per env step (timestep = env_dt / substeps)
    forward_m: float = 0.2  # FORWARD / BACKWARD displacement (m)
    turn_deg: float = 30.0  # TURN_LEFT / TURN_RIGHT rotation (deg)
    ramp_substeps: int = 3  # trapezoid velocity plan: substeps to reach cruise speed
    servo_gain: float = 0.5  # a = dt kv / m of the implicit velocity servos (see docstring)
    contact_skin: float = 0.02  # collision capsule = radius + skin: contacts start this far out
    contact_solref: tuple = (0.02, 1.0)  # timeconst >= 2 dt (MuJoCo's refsafe)
    contact_solimp: tuple = (0.95, 0.99, 0.001, 0.5, 2.0)  # stiff: little give under the servo push
    max_geom_pairs: int | None = None  # None: smallest K that never drops a live contact
    solver_iterations: int = 4  # Newton iterations (few frictionless contacts on 3 dofs)
    ls_iterations: int = 8
    collider: str = "sphere"  # 'sphere' (on prisms, see docstring) | 'capsule' (before 2026-12-02)
    physics: str = "auto"  # 'jax' | 'warp' | 'auto' (warp on NVIDIA GPUs when installed, else jax)
    warp_contacts_per_env: int = 8  # MJX-Warp's contact pool: this many per env, shared by all envs
    agent_rgba: tuple = (0.2, 0.4, 0.9, 1.0)


@struct.dataclass
class SimState:
    """What persists between env steps (module docstring): the physics model's time, qpos, qvel
    and solver warm start (mjx.Data's names), and the scene model's geom poses for the sensors."""

    time: jax.Array  # f32[]
    qpos: jax.Array  # f32[3] the agent's (x, y, yaw) joints, the same in both models
    qvel: jax.Array  # f32[3]
    qacc_warmstart: jax.Array  # f32[3]
    geom_xpos: jax.Array  # f32[ngeom, 3] of mj_model's geoms (objects where init placed them)
    geom_xmat: jax.Array  # f32[ngeom, 3, 3]


PHYSICS_FIELDS = ("time", "qpos", "qvel", "qacc_warmstart")  # SimState's fields of the physics model's Data


PHYSICS_IMPLS = ("auto", "jax", "warp")
COLLIDERS = ("sphere", "capsule")


def check_collider(collider: str) -> str:
    """`SimConfig.collider`, checked."""
    if collider not in COLLIDERS:
        raise ValueError(f"unknown collider {collider!r}; valid: {', '.join(COLLIDERS)}")
    return collider


def warp_installed() -> bool:
    """Whether MJX can use its Warp implementation (the `warp-lang` package imports)."""
    from mujoco.mjx import warp as mjx_warp

    return bool(mjx_warp.WARP_INSTALLED)


def resolve_physics(physics: str) -> str:
    """'jax' or 'warp': what `SimConfig.physics` runs on this machine ('auto': warp on an NVIDIA GPU
    with warp-lang installed, else jax)."""
    if physics not in PHYSICS_IMPLS:
        raise ValueError(f"unknown physics {physics!r}; valid: {', '.join(PHYSICS_IMPLS)}")
    if physics == "auto":
        nvidia = jax.default_backend() == "gpu" and "nvidia" in jax.devices()[0].device_kind.lower()
        return "warp" if nvidia and warp_installed() else "jax"
    if physics == "warp" and not warp_installed():
        raise ValueError(
            "physics 'warp' needs the warp-lang package: pip install -e '.[warp]' (or '.[cuda]' on "
            "NVIDIA GPUs), or choose physics 'jax'"
        )
    return physics


def velocity_plan(config: SimConfig) -> np.ndarray:
    """Planned velocity per unit displacement, u[0..N] (u_0 = u_N = 0, dt * sum(u) = 1)."""
    n = config.substeps
    dt = config.env_dt / n
    k = np.arange(n - 1)
    w = np.minimum(np.minimum(k + 1, n - 1 - k), config.ramp_substeps).astype(np.float64)
    u = np.concatenate([[0.0], w / (w.sum() * dt), [0.0]])
    return u


def control_profile(config: SimConfig) -> np.ndarray:
    """Per-substep velocity-servo command per unit displacement, c[0..N-1] (deadbeat on the plan)."""
    u = velocity_plan(config)
    a = config.servo_gain
    return ((1.0 + a) * u[1:] - u[:-1]) / a


def _add_agent(spec: mujoco.MjSpec, cfg: SimConfig) -> None:
    """Inject the agent body, its joints, visible capsule, collider sphere and velocity actuators."""
    dt = cfg.env_dt / cfg.substeps
    body = spec.worldbody.add_body(name=AGENT_BODY)
    for name, jtype, axis in (
        (AGENT_JOINTS[0], mujoco.mjtJoint.mjJNT_SLIDE, [1.0, 0.0, 0.0]),
        (AGENT_JOINTS[1], mujoco.mjtJoint.mjJNT_SLIDE, [0.0, 1.0, 0.0]),
        (AGENT_JOINTS[2], mujoco.mjtJoint.mjJNT_HINGE, [0.0, 0.0, 1.0]),
    ):
        body.add_joint(name=name, type=jtype, axis=axis)
    # Explicit inertia with the COM on the joint axes: the mass matrix is diag(m, m, Izz), which is
    # what the servo gains below assume.
    izz = 0.5 * cfg.mass * cfg.radius**2
    body.explicitinertial = True
    body.mass = cfg.mass
    body.inertia = [izz, izz, izz]
    z0 = cfg.bottom_clearance + cfg.radius
    z1 = cfg.height - cfg.radius
    capsule = cfg.collider == "capsule"  # the collision model of runs before 2026-12-02
    body_geom = body.add_geom(
        name=AGENT_GEOM,
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        size=[cfg.radius + (cfg.contact_skin if capsule else 0.0), 0.0, 0.0],
        fromto=[0.0, 0.0, z0, 0.0, 0.0, z1],
    )
    body_geom.rgba = list(cfg.agent_rgba)
    body_geom.contype, body_geom.conaffinity = 0, 0
    geom = body_geom
    if not capsule:
        # The collider: a sphere at mid-height against blockers that span the agent's whole height
        # (_physics_model), i.e. a cylinder against prisms in the plane the agent moves in.
        geom = body.add_geom(
            name=AGENT_COLLIDER,
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[cfg.radius + cfg.contact_skin, 0.0, 0.0],
            pos=[0.0, 0.0, 0.5 * (cfg.bottom_clearance + cfg.height)],
        )
        geom.rgba = [0.0, 0.0, 0.0, 0.0]  # invisible to rays and renderers
        geom.group = 3
    # Its radius is the body's plus a skin: MJX's colliders report only penetrating contacts (geom
    # margins are ignored), hence the early-contact zone is built into the radius.
    geom.condim = 1  # frictionless: turning in contact is free, walls are slid along
    geom.priority = 10  # the agent's contact parameters win over the scene's
    geom.solref = list(cfg.contact_solref)
    geom.solimp = list(cfg.contact_solimp)
    for jname, inertia in zip(AGENT_JOINTS, (cfg.mass, cfg.mass, izz)):
        act = spec.add_actuator(name=jname, target=jname, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_velocity(kv=cfg.servo_gain * inertia / dt)
    spec.option.timestep = dt
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.iterations = cfg.solver_iterations
    spec.option.ls_iterations = cfg.ls_iterations
    # placeholder, set after compile once the blocker set is known
    spec.add_numeric(name="max_geom_pairs", data=[-1.0])


def _geom_world_aabb(m: mujoco.MjModel, d: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
    """World AABB (center, half extents) of every geom (box, sphere, capsule), from d's kinematics."""
    half = np.zeros((m.ngeom, 3))
    for g in range(m.ngeom):
        rot = d.geom_xmat[g].reshape(3, 3)
        s = m.geom_size[g]
        t = m.geom_type[g]
        if t == mujoco.mjtGeom.mjGEOM_BOX:
            half[g] = np.abs(rot) @ s
        elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
            half[g] = s[0]
        elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
            half[g] = np.abs(rot[:, 2]) * s[1] + s[0]
        else:  # other types: bounding sphere
            half[g] = m.geom_rbound[g]
    return d.geom_xpos.copy(), half


def _physics_model(m: mujoco.MjModel, d: mujoco.MjData, blockers, cfg: SimConfig):
    """The model MJX steps: the agent and the blockers only. Returns (model, indices of the grown
    blockers in `m`). The blockers become geoms of the world body at their world poses (physics
    geom i is `m`'s geom blockers[i]), then `_add_agent` adds the agent's body, geoms and
    actuators; nothing else of the scene is in it (no room, no mocap object, no static body).

    Why only these: the agent is the one body that moves and the blockers the only geoms it
    touches, and MJX's step costs what the model holds, not what moves: kinematics, velocities and
    inertias of every body, every substep. With the scene's 121 bodies (house.xml) that was half of
    an env step's physics on the CPU, and for a GPU XLA fused MJX's per-body work into kernels over
    all bodies at once, the largest of which took 7.6 s to compile on its own (docs/benchmarks.md, Physics).
    The agent's motion is the same: the same shapes at the same world poses, and the agent's
    contact parameters win every pair (its geoms' priority).

    With the sphere collider (default), every upright blocker box (and vertical capsule) also grows
    about its centre in z until it spans the agent's height (+ 5 cm each way). With every blocker a
    prism over the agent's height, a sphere at mid-height (the agent's collider) meets each one
    exactly where a cylinder of the same radius would: collision is planar, as the agent's motion
    is. MJX's sphere-box collider is exact for that; its capsule-box collider is not: near a
    vertical box edge it drops the contact when the edge direction is within 8 deg of the nearest
    face's normal (it then prefers a face contact that the face's side planes clip away), and at
    boxes whose top lies within the capsule's height it can keep a horizontal edge that fails its
    Voronoi test: the agent walked 0.2 m into a bed corner where native MuJoCo stops it
    (tests/test_sim_native.py). Only contacts that a capsule would make with its rounded ends (box
    tops below 0.25 m, bottoms above 1.0 m) move out, by < 2.2 cm. Centres are unchanged.
    """
    zlo = cfg.bottom_clearance - cfg.contact_skin  # the agent's lowest point
    zhi = cfg.height + cfg.contact_skin  # and its highest
    G = mujoco.mjtGeom
    box, capsule, sphere = int(G.mjGEOM_BOX), int(G.mjGEOM_CAPSULE), int(G.mjGEOM_SPHERE)
    primitive = (box, capsule, sphere, int(G.mjGEOM_CYLINDER), int(G.mjGEOM_ELLIPSOID))  # size says all
    spec = mujoco.MjSpec()
    grown = []
    for g in blockers:
        kind = int(m.geom_type[g])  # ints throughout: numpy ints and MuJoCo's enums do not compare
        if kind not in primitive:
            raise ValueError(
                f"geom {m.geom(g).name or g} blocks the agent but is a {G(kind).name}; blockers "
                "must be boxes, capsules, spheres, cylinders or ellipsoids (docs/scene_format.md)"
            )
        rot = d.geom_xmat[g].reshape(3, 3)
        size = m.geom_size[g].copy()
        if cfg.collider == "sphere" and kind in (box, capsule):
            is_capsule = kind == capsule
            axis = 2 if is_capsule else int(np.abs(rot[2]).argmax())  # the local axis closest to z
            i = 1 if is_capsule else axis  # the size entry of that half extent (a capsule's segment)
            cz = d.geom_xpos[g, 2]
            # upright (tilted ones collide as they are) and not already spanning the agent's height
            if abs(rot[2, axis]) >= 1.0 - 1e-6 and (cz - size[i] > zlo or cz + size[i] < zhi):
                size[i] = max(cz - zlo, zhi - cz) + 0.05
                grown.append(g)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, d.geom_xmat[g])
        geom = spec.worldbody.add_geom(type=G(kind), size=size, pos=d.geom_xpos[g], quat=quat)
        geom.condim, geom.priority = int(m.geom_condim[g]), int(m.geom_priority[g])
        geom.solref, geom.solimp, geom.solmix = m.geom_solref[g], m.geom_solimp[g], float(m.geom_solmix[g])
        geom.margin, geom.gap = float(m.geom_margin[g]), float(m.geom_gap[g])
        geom.friction = m.geom_friction[g]
    _add_agent(spec, cfg)
    return spec.compile(), np.asarray(grown, np.int64)


def _auto_max_geom_pairs(m, d, agent_geom, blockers, cfg: SimConfig, grid: float = 0.05) -> int:
    """Smallest K for MJX's bounding-sphere top-K broadphase that keeps every possible contact.

    For agent positions on a grid covering the blockers' extent, a blocker can be in contact only if
    its AABB overlaps the collider's AABB; MJX ranks pairs by
    |c_agent - c_geom| - rbound_agent - rbound_geom. K = 1 + the worst rank of a possibly-touching
    blocker over all positions (ties counted against us).
    """
    if len(blockers) == 0:
        return 0
    c, h = _geom_world_aabb(m, d)
    cb, hb = c[blockers], h[blockers]
    lo = (cb - hb)[:, :2].min(0) - cfg.radius
    hi = (cb + hb)[:, :2].max(0) + cfg.radius
    xs = np.arange(lo[0], hi[0] + grid, grid)
    ys = np.arange(lo[1], hi[1] + grid, grid)
    zc, zh = c[agent_geom, 2], h[agent_geom, 2]
    rb = m.geom_rbound[blockers]
    rb_agent = m.geom_rbound[agent_geom]
    reach = cfg.radius + cfg.contact_skin
    z_overlap = np.abs(cb[:, 2] - zc) <= hb[:, 2] + zh
    worst = 0
    for x in xs:  # one row of the grid at a time keeps memory at len(ys) x len(blockers)
        p = np.stack([np.full_like(ys, x), ys, np.full_like(ys, zc)], -1)  # (Y, 3)
        metric = np.linalg.norm(p[:, None] - cb[None], axis=-1) - rb[None] - rb_agent  # (Y, B)
        touch = (
            (np.abs(p[:, None, 0] - cb[None, :, 0]) <= hb[None, :, 0] + reach)
            & (np.abs(p[:, None, 1] - cb[None, :, 1]) <= hb[None, :, 1] + reach)
            & z_overlap[None]
        )
        if not touch.any():
            continue
        # rank of a touching blocker = number of blockers with metric <= its metric (itself included)
        worst_metric = np.where(touch, metric, -np.inf).max(1)  # (Y,)
        rank = (metric <= worst_metric[:, None]).sum(1)
        worst = max(worst, int(rank[touch.any(1)].max()))
    return worst


class Simulator:
    """Static container for one compiled scene + agent; all methods are pure and jittable.

    Attributes of the scene model: `mj_model` (mujoco.MjModel, the scene file + the agent: what the
    camera, placement and geodesic map read), `scene_ngeom` (the scene file's geoms are geoms
    [0, scene_ngeom), the agent's come after), `agent_geoms` (np int), `agent_body`, `blockers` (np
    int: geoms that block the agent), `grown_blockers` (those the physics model grows), `nmocap`,
    `default_mocap_pos` / `default_mocap_quat` (the file's mocap poses).
    Of the physics model: `physics_model` (the agent and the blockers only, `_physics_model`; what
    MJX steps, and what native references must step), `mjx_model` (it on the device; the scene
    model's is `scene_mjx_model`),
    `physics_blockers` (its geoms of `blockers`, in that order), `collider_geom` (its agent geom
    that collides), `max_geom_pairs`. Both models have the agent's three joints as their only
    degrees of freedom, so qpos / qvel mean the same in both.
    """

    def __init__(self, spec: mujoco.MjSpec, config: SimConfig = SimConfig()):
        cfg = config
        if cfg.substeps < 3:
            raise ValueError("substeps must be >= 3 for the velocity plan")
        check_collider(cfg.collider)
        scene_model = spec.compile()
        self.scene_ngeom = scene_model.ngeom
        if scene_model.nq or scene_model.nv:
            raise ValueError(
                f"the scene has {scene_model.nq} joint coordinates; scene bodies must be static or "
                "mocap (docs/scene_format.md): the agent is the only body that moves"
            )
        _add_agent(spec, cfg)
        m = spec.compile()
        if not np.array_equal(m.geom_type[: self.scene_ngeom], scene_model.geom_type):
            raise RuntimeError("adding the agent reordered the scene's geoms")
        if m.nmat < 1:  # mjx.ray needs at least one material; add one rather than fail
            spec.add_material(name="hron_default")
            m = spec.compile()
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)

        self.config = cfg
        self.agent_body = m.body(AGENT_BODY).id
        self.agent_geoms = np.nonzero(m.geom_bodyid == self.agent_body)[0]
        self.qpos_adr = np.array([m.jnt_qposadr[m.joint(j).id] for j in AGENT_JOINTS])
        self.dof_adr = np.array([m.jnt_dofadr[m.joint(j).id] for j in AGENT_JOINTS])

        # --- what blocks the agent: every scene geom that is no floor, no mocap object, and reaches
        # into its height range ---
        body_names = [m.body(b).name for b in range(m.nbody)]
        root = m.body_rootid
        is_floor = np.array([body_names[root[m.geom_bodyid[g]]].startswith("room:") for g in range(m.ngeom)])
        is_mocap = m.body_mocapid[root[m.geom_bodyid]] >= 0
        c, h = _geom_world_aabb(m, d)
        reaches = (c[:, 2] + h[:, 2] > cfg.bottom_clearance - cfg.contact_skin) & (
            c[:, 2] - h[:, 2] < cfg.height + cfg.contact_skin
        )
        is_scene = np.arange(m.ngeom) < self.scene_ngeom
        self.blockers = np.nonzero(is_scene & ~is_floor & ~is_mocap & reaches)[0]

        # --- the physics model; both models get the contact filter (the geodesic map reads the
        # scene model's): agent collider (contype 1) x blockers (conaffinity 1), nothing else ---
        mp, self.grown_blockers = _physics_model(m, d, self.blockers, cfg)
        self.physics_blockers = np.arange(len(self.blockers))
        collider = AGENT_GEOM if cfg.collider == "capsule" else AGENT_COLLIDER
        self.collider_geom = mp.geom(collider).id
        for model, blockers in ((m, self.blockers), (mp, self.physics_blockers)):
            model.geom_contype[:] = 0
            model.geom_conaffinity[:] = 0
            model.geom_conaffinity[blockers] = 1
            model.geom_contype[model.geom(collider).id] = 1
        dp = mujoco.MjData(mp)
        mujoco.mj_kinematics(mp, dp)
        k = cfg.max_geom_pairs
        if k is None:
            k = _auto_max_geom_pairs(mp, dp, self.collider_geom, self.physics_blockers, cfg)
        k = int(max(1, min(k, max(len(self.blockers), 1))))
        mp.numeric_data[mp.numeric("max_geom_pairs").adr[0]] = float(k)
        self.max_geom_pairs = k

        self.mj_model = m
        self.physics_model = mp
        self.mjx_model = mjx.put_model(mp)
        self.physics = resolve_physics(cfg.physics)
        self._warp = None
        if self.physics == "warp":
            from hron_jax.sim_warp import WarpPhysics

            self._warp = WarpPhysics(mp, cfg.warp_contacts_per_env)
        self.nmocap = m.nmocap
        self.default_mocap_pos = (
            np.array(m.body_pos[m.body_mocapid >= 0][np.argsort(m.body_mocapid[m.body_mocapid >= 0])])
            if m.nmocap
            else np.zeros((0, 3))
        )
        self.default_mocap_quat = (
            np.array(m.body_quat[m.body_mocapid >= 0][np.argsort(m.body_mocapid[m.body_mocapid >= 0])])
            if m.nmocap
            else np.zeros((0, 4))
        )
        self._template = mjx.put_data(mp, mujoco.MjData(mp))
        self.scene_mjx_model = mjx.put_model(m)
        self._scene_template = mjx.put_data(m, mujoco.MjData(m))
        # The agent's geoms in its body frame (the body sits at the world origin at qpos 0), so the
        # scene's geom poses follow the agent after every step without the scene's kinematics.
        self._agent_geom_pos = np.asarray(d.geom_xpos[self.agent_geoms], np.float32)
        self._agent_geom_mat = np.asarray(d.geom_xmat[self.agent_geoms], np.float32).reshape(-1, 3, 3)
        self._ctrl_profile = jnp.asarray(control_profile(cfg), jnp.float32)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_file(cls, path: str | os.PathLike, config: SimConfig = SimConfig()) -> Simulator:
        return cls(mujoco.MjSpec.from_file(os.fspath(path)), config)

    @classmethod
    def from_xml(cls, xml: str, config: SimConfig = SimConfig()) -> Simulator:
        return cls(mujoco.MjSpec.from_string(xml), config)

    # ------------------------------------------------------------------ functional API
    def init(
        self, pose: jax.Array, mocap_pos: jax.Array | None = None, mocap_quat: jax.Array | None = None
    ) -> SimState:
        """The agent at pose (x, y, yaw) at rest, with the given mocap poses (default: the file's).

        Runs the scene's kinematics once, for the geom poses the sensors read (mocap objects
        included); the physics model starts from its blank data at that pose."""
        d = self._scene_template
        qpos = d.qpos.at[self.qpos_adr].set(jnp.asarray(pose, d.qpos.dtype))
        repl = dict(qpos=qpos)
        if mocap_pos is not None:
            repl["mocap_pos"] = jnp.asarray(mocap_pos, d.mocap_pos.dtype).reshape(d.mocap_pos.shape)
        if mocap_quat is not None:
            repl["mocap_quat"] = jnp.asarray(mocap_quat, d.mocap_quat.dtype).reshape(d.mocap_quat.shape)
        scene = mjx.kinematics(self.scene_mjx_model, d.replace(**repl))
        p = self._template
        return SimState(
            time=p.time,
            qpos=qpos,
            qvel=p.qvel,
            qacc_warmstart=p.qacc_warmstart,
            geom_xpos=scene.geom_xpos,
            geom_xmat=scene.geom_xmat,
        )

    def data(self, state: SimState) -> mjx.Data:
        """The physics model's full mjx.Data that `state` stands for: its blank data with the
        persistent fields set."""
        return self._template.replace(**{f: getattr(state, f) for f in PHYSICS_FIELDS})

    def action_delta(self, pose: jax.Array, action: jax.Array) -> jax.Array:
        """World-frame (dx, dy, dyaw) that `action` asks for at `pose` (x, y, yaw)."""
        cfg = self.config
        yaw = pose[2]
        fwd = jnp.stack([jnp.cos(yaw), jnp.sin(yaw)]) * cfg.forward_m
        turn = math.radians(cfg.turn_deg)
        table = jnp.stack(
            [
                jnp.concatenate([fwd, jnp.zeros(1)]),
                jnp.concatenate([-fwd, jnp.zeros(1)]),
                jnp.array([0.0, 0.0, turn]),
                jnp.array([0.0, 0.0, -turn]),
                jnp.zeros(3),
            ]
        )
        return table[jnp.clip(action, 0, NUM_ACTIONS - 1)]

    def step(self, state: SimState, action: jax.Array) -> SimState:
        """Execute one discrete action: `substeps` MJX steps (env_dt seconds), then brake; the
        agent's geoms in the scene's geom poses move with it."""
        d = self.step_data(self.data(state), action)
        xpos, xmat = self.agent_geom_poses(d.qpos)
        return SimState(
            **{f: getattr(d, f) for f in PHYSICS_FIELDS},
            geom_xpos=state.geom_xpos.at[self.agent_geoms].set(xpos.astype(state.geom_xpos.dtype)),
            geom_xmat=state.geom_xmat.at[self.agent_geoms].set(xmat.astype(state.geom_xmat.dtype)),
        )

    def step_data(self, data: mjx.Data, action: jax.Array) -> mjx.Data:
        """`step` on the physics model's full mjx.Data (what `step` runs; the reference its state is
        tested against)."""
        pose = data.qpos[self.qpos_adr]
        delta = self.action_delta(pose, action).astype(data.ctrl.dtype)
        ctrl = self._ctrl_profile.astype(data.ctrl.dtype)[:, None] * delta  # (substeps, nu)
        if self._warp is None:
            data, _ = jax.lax.scan(
                lambda d, c: (mjx.step(self.mjx_model, d.replace(ctrl=c)), None), data, ctrl
            )
        else:  # a batch of one world; vmapped callers step all worlds in one call (sim_warp)
            args = (data.qpos, data.qvel, data.time, ctrl)
            out = self._warp.substeps(*(a[None] for a in args))
            data = data.replace(**{f: x[0] for f, x in out.items()})
        # Brake: whatever contacts did, nothing carries into the next action.
        return data.replace(qvel=data.qvel.at[self.dof_adr].set(0.0), ctrl=jnp.zeros_like(data.ctrl))

    def agent_geom_poses(self, qpos: jax.Array) -> tuple[jax.Array, jax.Array]:
        """World poses (xpos f32[G, 3], xmat f32[G, 3, 3]) of the agent's geoms (`agent_geoms`) at
        qpos: the slide joints translate its body in x, y and the hinge turns it about z."""
        x, y, yaw = (qpos[a] for a in self.qpos_adr)
        c, s = jnp.cos(yaw), jnp.sin(yaw)
        zero, one = jnp.zeros_like(c), jnp.ones_like(c)
        rot = jnp.stack([jnp.stack([c, -s, zero]), jnp.stack([s, c, zero]), jnp.stack([zero, zero, one])])
        xpos = self._agent_geom_pos @ rot.T + jnp.stack([x, y, zero])
        return xpos, rot @ self._agent_geom_mat

    def agent_pose(self, data: SimState | mjx.Data) -> jax.Array:
        """(x, y, yaw) with yaw wrapped to [-pi, pi)."""
        p = data.qpos[self.qpos_adr]
        yaw = jnp.mod(p[2] + jnp.pi, 2 * jnp.pi) - jnp.pi
        return jnp.stack([p[0], p[1], yaw])

    def agent_velocity(self, data: SimState | mjx.Data) -> jax.Array:
        """(vx, vy, wz): zero after every `step` (the brake)."""
        return data.qvel[self.dof_adr]

    def geom_tables(self, geom_instance: np.ndarray, geom_class: np.ndarray):
        """Extend the scene's (scene_ngeom,) instance / class tables to the full model (agent: -1, 0)."""
        gi = np.full(self.mj_model.ngeom, -1, np.int32)
        gc = np.zeros(self.mj_model.ngeom, np.int32)
        gi[: self.scene_ngeom] = geom_instance
        gc[: self.scene_ngeom] = geom_class
        return gi, gc
