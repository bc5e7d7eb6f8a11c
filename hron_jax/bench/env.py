"""Simulator + camera env steps/s vs native MuJoCo (`python -m hron_jax.bench env`).

Measures env steps/s of jitted, vmapped MJX physics (`Simulator.step`, 0.1 s of sim = `substeps`
MJX steps) and of the ray-cast camera per backend, for each --num-envs; and the same work done by
native MuJoCo in a Python loop (mj_step substeps + mj_multiRay on the same rays, numpy lookups),
with the ratio. Poses are random collision-free positions of the scene (seeded), actions are
uniform over the 5 actions. Per num_envs B:
    physics     jit(vmap(sim.step)) on B envs, per --physics implementation (MJX = its JAX
                implementation, MJX-Warp = SimConfig.physics 'warp') and --collider model
    render/<b>  jit(vmap(camera.render)) on B envs, backend b in
                kernel (column- and band-culled analytic kernel, CameraConfig.k_box /
                k_band), kernel-rank (the same picking candidates without a sort,
                CameraConfig.select), kernel-columns (the same with one band per column: what the row
                bands buy), kernel-nocull (same kernel testing every geom: what culling buys),
                mjx (mjx.ray per pixel)
    env/<b>     physics then render, the two jitted calls back to back (what an env step costs)
    native      one MjData per env, a Python loop over envs: `substeps` x mj_step with the same
                controls, brake, then mj_multiRay for the same H x W rays and numpy lookups for
                depth / instance / class; native steps/s do not depend on B (one core).
Times are wall-clock over --steps calls after one warm-up call (compile excluded; compile times go
to stderr). Each timing is the best of --repeats runs, since the machine may be shared. Native is
measured first, so that every row can carry its native steps/s and ratio.

Prints: the scene and camera, then the Markdown table | num_envs | what | ms / batch step |
env steps / s | native steps / s | ratio |, a row as soon as it is measured, the native rows last.
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import numpy as np

from .common import DEFAULT_SCENE, best_time, progress, stream_table, time_calls, timed


def synthetic_house_xml(n_boxes: int = 300, seed: int = 0, rooms: int = 3) -> str:
    """A house-like annotated scene of about `n_boxes` boxes: `rooms` x `rooms` rooms on a grid with
    walls (door gaps) and random furniture made of boxes, plus a few mocap objects."""
    rng = np.random.default_rng(seed)
    size = 4.0
    L = rooms * size
    cats = ["kitchen", "living_room", "bedroom", "office", "bathroom", "dining_room", "corridor"]
    out = [
        '<mujoco model="synthetic_house"><compiler angle="degree"/>',
        '<asset><material name="plain" rgba="1 1 1 1"/></asset><worldbody>',
    ]
    k_room = {}
    for i in range(rooms):
        for j in range(rooms):
            c = cats[(i * rooms + j) % len(cats)]
            k = k_room.setdefault(c, 0)
            k_room[c] += 1
            cx, cy = (i + 0.5) * size, (j + 0.5) * size
            out.append(
                f'<body name="room:{c}:{k}"><geom type="box" pos="{cx} {cy} -0.025" '
                f'size="{size / 2} {size / 2} 0.025" rgba="0.7 0.6 0.5 1"/></body>'
            )
    nb = 0
    for i in range(rooms + 1):  # grid lines x = i * size and y = i * size
        for j in range(rooms):  # one room side per (line, cell); interior sides get a 1 m door
            b0, b1 = j * size, (j + 1) * size
            spans = [(b0, b1)] if i in (0, rooms) else [(b0, b0 + size / 2 - 0.5), (b0 + size / 2 + 0.5, b1)]
            for lo, hi in spans:
                mid, half = (lo + hi) / 2, (hi - lo) / 2 + 0.05
                a = i * size
                for pos, sz in (
                    (f"{mid} {a} 1.25", f"{half} 0.05 1.25"),
                    (f"{a} {mid} 1.25", f"0.05 {half} 1.25"),
                ):
                    out.append(f'<geom type="box" pos="{pos}" size="{sz}" rgba="0.9 0.9 0.85 1"/>')
                    nb += 1
    k_f = 0
    while nb < n_boxes - 4:
        x, y = rng.uniform(0.8, L - 0.8, 2)
        yaw = rng.choice([0.0, 90.0, rng.uniform(0, 180)])
        w, dpt, h = rng.uniform(0.3, 0.8), rng.uniform(0.2, 0.5), rng.uniform(0.4, 1.0)
        parts = [(0, 0, h, w, dpt, 0.02)] + [
            (sx * (w - 0.03), sy * (dpt - 0.03), h / 2, 0.03, 0.03, h / 2) for sx in (-1, 1) for sy in (-1, 1)
        ]
        out.append(f'<body name="furniture:table:{k_f}" pos="{x:.3f} {y:.3f} 0" euler="0 0 {yaw:.1f}">')
        for px, py, pz, hx, hy, hz in parts:
            out.append(
                f'<geom type="box" pos="{px:.3f} {py:.3f} {pz:.3f}" size="{hx:.3f} {hy:.3f} {hz:.3f}" '
                f'rgba="0.5 0.35 0.2 1"/>'
            )
        out.append('</body>')
        nb += len(parts)
        k_f += 1
    for k in range(4):
        out.append(
            f'<body name="object:apple:{k}" mocap="true" pos="{k} 0 -5"><geom type="sphere" '
            f'size="0.045" rgba="0.8 0.1 0.1 1"/></body>'
        )
    out.append("</worldbody></mujoco>")
    return "\n".join(out)


def _free_poses(sim, n: int, rng: np.random.Generator) -> np.ndarray:
    """n random (x, y, yaw) where the agent touches no blocker (native collision check)."""
    import mujoco

    ms, ds = sim.mj_model, mujoco.MjData(sim.mj_model)
    mujoco.mj_kinematics(ms, ds)
    floor = [g for g in range(sim.scene_ngeom) if g not in set(sim.blockers)]
    pts = ds.geom_xpos[floor if floor else list(range(sim.scene_ngeom)), :2]
    lo, hi = pts.min(0), pts.max(0)
    m = sim.physics_model
    d = mujoco.MjData(m)
    out = []
    while len(out) < n:
        d.qpos[sim.qpos_adr] = [*rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi)]
        mujoco.mj_fwdPosition(m, d)
        if d.ncon == 0:
            out.append(d.qpos[sim.qpos_adr].copy())
    return np.asarray(out, np.float32)


class _Native:
    """The same env step in native MuJoCo: substeps x mj_step + brake + mj_multiRay + lookups."""

    def __init__(self, sim, cam, poses: np.ndarray):
        import mujoco

        from .. import sensors as SN
        from .. import sim as S

        self.mujoco, self.sim, self.cam = mujoco, sim, cam
        self.m = sim.physics_model  # what MJX steps; rays go to the scene as it is
        self.m_scene = sim.mj_model
        # The scene's geom poses: static, and the agent's own are excluded from the rays.
        self.d_scene = mujoco.MjData(self.m_scene)
        mujoco.mj_kinematics(self.m_scene, self.d_scene)
        self.datas = []
        for p in poses:
            d = mujoco.MjData(self.m)
            d.qpos[sim.qpos_adr] = p
            mujoco.mj_forward(self.m, d)
            self.datas.append(d)
        self.ctrl = S.control_profile(sim.config)
        self.turn = np.radians(sim.config.turn_deg)
        self.fwd = sim.config.forward_m
        self.dirs_cam = SN.pixel_directions(cam.config).reshape(-1, 3).astype(np.float64)
        self.nray = len(self.dirs_cam)
        self.gid = np.zeros(self.nray, np.int32)
        self.dist = np.zeros(self.nray)
        self.inst = np.asarray(cam.geom_instance)
        self.cls = np.asarray(cam.geom_class)
        self.rgb = np.asarray(cam.geom_rgb)

    def physics(self, d, action: int):
        mj = self.mujoco
        q = d.qpos[self.sim.qpos_adr]
        c, s = np.cos(q[2]), np.sin(q[2])
        delta = [
            np.array([c, s, 0]) * self.fwd,
            -np.array([c, s, 0]) * self.fwd,
            np.array([0, 0, self.turn]),
            np.array([0, 0, -self.turn]),
            np.zeros(3),
        ][action]
        for cn in self.ctrl:
            d.ctrl[:] = delta * cn
            mj.mj_step(self.m, d)
        d.qvel[self.sim.dof_adr] = 0.0

    def render(self, d):
        cfg = self.cam.config
        x, y, yaw = d.qpos[self.sim.qpos_adr]
        p = np.radians(cfg.pitch_deg)
        cy, sy = np.cos(yaw), np.sin(yaw)
        rot = np.stack(
            [
                [sy, -cy, 0.0],
                [-cy * np.sin(p), -sy * np.sin(p), np.cos(p)],
                [cy * np.cos(p), sy * np.cos(p), np.sin(p)],
            ],
            1,
        )
        o = np.array([x + cfg.forward_offset * cy, y + cfg.forward_offset * sy, cfg.mount_height])
        vec = (self.dirs_cam @ rot.T).ravel()
        self.mujoco.mj_multiRay(
            self.m_scene,
            self.d_scene,
            o,
            vec,
            None,
            1,
            self.sim.agent_body,
            self.gid,
            self.dist,
            None,
            self.nray,
            cfg.max_depth,
        )
        hit = (self.gid >= 0) & (self.dist <= cfg.max_depth)
        g = np.where(hit, self.gid, 0)
        depth = np.where(hit, self.dist, cfg.max_depth)
        return depth, np.where(hit, self.inst[g], -1), np.where(hit, self.cls[g], 0), self.rgb[g]

    def time(self, actions: np.ndarray, what: str, repeats: int) -> float:
        """Best seconds per env step over the (T, B) actions."""

        def run():
            for row in actions:
                for d, a in zip(self.datas, row):
                    if what in ("physics", "env"):
                        self.physics(d, int(a))
                    if what in ("render", "env"):
                        self.render(d)

        return best_time(run, repeats) / actions.size


def bench_env(
    scene_path: str | None,
    num_envs=(1, 16, 64),
    steps: int = 20,
    repeats: int = 3,
    width: int = 32,
    height: int = 32,
    backends=("kernel", "kernel-nocull", "mjx"),
    native_envs: int = 8,
    seed: int = 0,
    log=progress,
    physics=("jax",),
    colliders=("sphere",),
):
    """Yields rows {num_envs, what, s_per_batch, steps_per_s, native_steps_per_s, ratio}, each as
    soon as it is measured (see the module docstring). One physics / env row per (physics,
    collider) pair; render rows and native rows use the first pair's model."""
    import jax
    import jax.numpy as jnp

    from .. import sensors as SN
    from ..sim import SimConfig, Simulator

    def simulator(impl, collider):
        cfg = SimConfig(physics=impl, collider=collider)
        return (
            Simulator.from_file(scene_path, cfg)
            if scene_path
            else Simulator.from_xml(synthetic_house_xml(), cfg)
        )

    label = {"jax": "MJX", "warp": "MJX-Warp"}
    sims = {  # row label -> Simulator
        label[impl] + (f", {collider} collider" if len(colliders) > 1 else ""): simulator(impl, collider)
        for collider in colliders
        for impl in physics
    }
    sim = next(iter(sims.values()))
    if scene_path:
        try:
            from ..scenes import load_scene

            scene = load_scene(scene_path)
        except Exception:  # unannotated file: generic tables
            scene = None
    else:
        scene = None
    m = sim.mj_model
    print(
        f"scene: {scene_path or 'synthetic_house_xml()'}: {m.ngeom} geoms "
        f"({np.bincount(m.geom_type, minlength=7)[[6, 2, 3]].tolist()} box/sphere/capsule), "
        f"{len(sim.blockers)} blockers, MJX max_geom_pairs K="
        + " / ".join(f"{s.max_geom_pairs} ({name})" for name, s in sims.items())
        + f", {sim.config.substeps} substeps/step",
        flush=True,
    )
    rng = np.random.default_rng(seed)
    base = SN.CameraConfig(width=width, height=height)
    n_box = int((m.geom_type == 6).sum())
    cfgs = {}
    for b in backends:
        if b == "kernel":
            cfg = base
        elif b == "kernel-columns":
            cfg = dataclasses.replace(base, row_bands=1, k_band=base.k_box)
        elif b == "kernel-rank":
            cfg = dataclasses.replace(base, select="rank")
        elif b == "kernel-nocull":
            cfg = dataclasses.replace(base, k_box=n_box, k_sphere=m.ngeom, k_capsule=m.ngeom, k_band=n_box)
        elif b == "mjx":
            cfg = dataclasses.replace(base, backend="mjx")
        else:
            raise ValueError(f"unknown backend {b!r}")
        cfgs[b] = cfg
    # a camera per collider (its model has one agent geom more or less), shared by the physics
    models = {}
    for s in sims.values():
        models.setdefault(s.config.collider, s)
    cams = {(c, b): SN.Camera.for_simulator(s, cfgs[b], scene=scene) for c, s in models.items() for b in cfgs}
    print(
        f"camera: {width}x{height}, vfov {base.vfov_deg} deg, max_depth {base.max_depth} m, "
        f"k_box {base.k_box}",
        flush=True,
    )

    # random inputs drawn in a fixed order (per B: poses, actions; then native), native timed first
    inputs = [
        (B, _free_poses(sim, B, rng), rng.integers(0, 5, size=(steps, B)).astype(np.int32)) for B in num_envs
    ]
    first = next(iter(sims))
    nat = _Native(sim, cams[sim.config.collider, backends[0]], _free_poses(sim, native_envs, rng))
    nat_acts = rng.integers(0, 5, size=(max(steps // 2, 2), native_envs))
    nat_t = {w: nat.time(nat_acts, w, repeats) for w in ("physics", "render", "env")}

    def row(B, what, s_per_batch, kind):
        sps, native = B / s_per_batch, 1.0 / nat_t[kind]
        return dict(
            num_envs=B,
            what=what,
            s_per_batch=s_per_batch,
            steps_per_s=sps,
            native_steps_per_s=native,
            ratio=sps / native,
        )

    fns = {
        name: (jax.jit(jax.vmap(s.init)), jax.jit(jax.vmap(s.step)), jax.jit(jax.vmap(s.agent_pose)))
        for name, s in sims.items()
    }
    for B, poses, acts in inputs:

        def run_phys(d, step):  # a chain of steps (each call consumes the previous data)
            for a in acts:
                d = step(d, jnp.asarray(a))
            return d

        d0 = {name: init(jnp.asarray(poses)) for name, (init, _, _) in fns.items()}
        for name, (_, step, _) in fns.items():
            _, t_c = timed(lambda: step(d0[name], jnp.asarray(acts[0])))
            log(f"B={B}: physics ({name}) compile {t_c:.1f} s")
            t = best_time(lambda: run_phys(d0[name], step), repeats) / steps
            yield row(B, f"physics ({name})", t, "physics")
        # the first model's end state: every render row renders the same frames
        d_end = run_phys(d0[first], fns[first][1])
        p_end = fns[first][2](d_end)

        for b in backends:
            rend = {c: jax.jit(jax.vmap(cams[c, b].render)) for c in models}
            own = rend[sim.config.collider]
            out, t_c = timed(lambda: own(d_end, p_end))
            log(
                f"B={B}: render/{b} compile {t_c:.1f} s, "
                f"uncertain rays {int(np.asarray(out.uncertain).sum())}"
            )
            yield row(B, f"render/{b}", time_calls(own, [(d_end, p_end)] * steps, repeats), "render")

            for name, (_, _, pose_fn) in fns.items():  # the other colliders' cameras compile here
                if sims[name].config.collider != sim.config.collider:
                    jax.block_until_ready(rend[sims[name].config.collider](d0[name], pose_fn(d0[name])))
            for name, (_, step, pose_fn) in fns.items():

                def run_env(d, step=step, rend=rend[sims[name].config.collider], pose_fn=pose_fn):
                    for a in acts:
                        d = step(d, jnp.asarray(a))
                        o = rend(d, pose_fn(d))
                    return d, o

                what = f"env/{b}" + (f" ({name})" if len(fns) > 1 else "")
                yield row(B, what, best_time(lambda: run_env(d0[name]), repeats) / steps, "env")

    # native MuJoCo reference (single core, Python loop over envs), measured above
    for w, what in (
        ("physics", "native physics (mj_step loop)"),
        ("render", "native render (mj_multiRay)"),
        ("env", "native env"),
    ):
        yield row(native_envs, what, nat_t[w] * native_envs, w)


HEADER = (
    "| num_envs | what | ms / batch step | env steps / s | native steps / s | ratio |\n"
    "| ---: | --- | ---: | ---: | ---: | ---: |"
)


def format_row(r: dict) -> str:
    return (
        f"| {r['num_envs']} | {r['what']} | {1e3 * r['s_per_batch']:.1f} | "
        f"{r['steps_per_s']:.0f} | {r['native_steps_per_s']:.0f} | {r['ratio']:.2f} |"
    )


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scene",
        default=DEFAULT_SCENE if os.path.exists(DEFAULT_SCENE) else None,
        help="scene file (default scenes/house.xml); 'synthetic' for a ~300-box house",
    )
    p.add_argument("--num-envs", type=int, nargs="+", default=[1, 16, 64])
    p.add_argument("--steps", type=int, default=20, help="timed calls per measurement")
    p.add_argument("--repeats", type=int, default=3, help="best of this many timed runs")
    p.add_argument("--width", type=int, default=32)
    p.add_argument("--height", type=int, default=32)
    p.add_argument(
        "--backends",
        nargs="+",
        default=["kernel", "kernel-nocull", "mjx"],
        choices=["kernel", "kernel-rank", "kernel-columns", "kernel-nocull", "mjx"],
    )
    p.add_argument("--native-envs", type=int, default=8)
    p.add_argument(
        "--physics", nargs="+", default=["jax"], choices=["jax", "warp"], help="MJX implementation(s)"
    )
    p.add_argument(
        "--collider",
        nargs="+",
        default=["sphere"],
        choices=["sphere", "capsule"],
        help="SimConfig.collider(s): the agent's collision model",
    )


def run(a: argparse.Namespace) -> None:
    scene = None if a.scene in (None, "synthetic") else a.scene
    stream_table(
        HEADER,
        bench_env(
            scene,
            tuple(a.num_envs),
            a.steps,
            a.repeats,
            a.width,
            a.height,
            tuple(a.backends),
            a.native_envs,
            physics=tuple(a.physics),
            colliders=tuple(a.collider),
        ),
        format_row,
    )
