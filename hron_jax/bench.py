"""Benchmarks: `python -m hron_jax.bench <subcommand>`.

Role: one argparse entry point with a subcommand per stage of the pipeline; each prints a Markdown
table and the machine it ran on. Subcommands register in `_SUBCOMMANDS` (name -> (add_args, run)).

    env     simulator + camera throughput (this module): env steps/s of jitted, vmapped MJX physics
            (`Simulator.step`, 0.1 s of sim = `substeps` MJX steps) and of the ray-cast camera per
            backend, for each --num-envs; and the same work done by native MuJoCo in a Python loop
            (mj_step substeps + mj_multiRay on the same rays, numpy lookups), with the ratio.
    graph   scene-graph / metric-map update cost (delegates to hron_jax.bench_graph).
    train   PPO training throughput (env + update) of train.py's program, per --num-envs
            (function `bench_train` below).
    model   forward and forward+grad ms of every model variant on a batch of house scene graphs
            (`bench_model`: round-robin over variants, median of --reps).
    conv    fwd+grad of the RGB-D conv stack inside lax.scan vs unrolled, nn.Conv vs PatchConv
            (`bench_conv`: the measurement behind models.encoders.PatchConv).

`env` in detail. Poses are random collision-free positions of the scene (seeded), actions are
uniform over the 5 actions. Per num_envs B:
    physics     jit(vmap(sim.step)) on B envs
    render/<b>  jit(vmap(camera.render)) on B envs, backend b in
                kernel (column-culled analytic kernel, CameraConfig.k_box), kernel-nocull
                (same kernel testing every geom: what culling buys), mjx (mjx.ray per pixel)
    env/<b>     physics then render, the two jitted calls back to back (what an env step costs)
    native      one MjData per env, a Python loop over envs: `substeps` x mj_step with the same
                controls, brake, then mj_multiRay for the same H x W rays and numpy lookups for
                depth / instance / class; native steps/s do not depend on B (one core).
Times are wall-clock over --steps calls after one warm-up call (compile excluded; compile times are
printed). Each timing is the best of --repeats runs, since the machine may be shared.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_DEFAULT_SCENE = os.path.join(_ROOT, "scenes", "house.xml")


# ---------------------------------------------------------------------------------------------
# machine description

def machine() -> dict:
    """The machine a measurement ran on: CPU model, logical / usable cores, 1-min load averages,
    Python, and (where JAX imports) its version and devices."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    out = {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
           "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()}
    if hasattr(os, "getloadavg"):
        out["loadavg"] = [round(x, 2) for x in os.getloadavg()]
    try:
        import jax
        out["jax"] = jax.__version__
        out["devices"] = [str(d) for d in jax.devices()]
        out["device_kind"] = f"{jax.devices()[0].platform} ({jax.devices()[0].device_kind})"
    except Exception:   # a report without JAX (e.g. reproduce.py --plan on a bare machine)
        pass
    return out


def machine_info() -> str:
    m = machine()
    load = ", load avg %.1f %.1f %.1f" % tuple(m["loadavg"]) if "loadavg" in m else ""
    return (f"CPU: {m['cpu']}, {m['cores']} logical cores ({m['usable_cores']} usable){load}; "
            f"jax {m.get('jax', '?')} on {m.get('device_kind', '?')}")


# ---------------------------------------------------------------------------------------------
# synthetic scene (used when no scene file is given / for quick tests)

def synthetic_house_xml(n_boxes: int = 300, seed: int = 0, rooms: int = 3) -> str:
    """A house-like annotated scene of about `n_boxes` boxes: `rooms` x `rooms` rooms on a grid with
    walls (door gaps) and random furniture made of boxes, plus a few mocap objects."""
    rng = np.random.default_rng(seed)
    size = 4.0
    L = rooms * size
    cats = ["kitchen", "living_room", "bedroom", "office", "bathroom", "dining_room", "corridor"]
    out = ['<mujoco model="synthetic_house"><compiler angle="degree"/>',
           '<asset><material name="plain" rgba="1 1 1 1"/></asset><worldbody>']
    k_room = {}
    for i in range(rooms):
        for j in range(rooms):
            c = cats[(i * rooms + j) % len(cats)]
            k = k_room.setdefault(c, 0)
            k_room[c] += 1
            cx, cy = (i + 0.5) * size, (j + 0.5) * size
            out.append(f'<body name="room:{c}:{k}"><geom type="box" pos="{cx} {cy} -0.025" '
                       f'size="{size / 2} {size / 2} 0.025" rgba="0.7 0.6 0.5 1"/></body>')
    nb = 0
    for i in range(rooms + 1):      # grid lines x = i * size and y = i * size
        for j in range(rooms):      # one room side per (line, cell); interior sides get a 1 m door
            b0, b1 = j * size, (j + 1) * size
            spans = [(b0, b1)] if i in (0, rooms) else [(b0, b0 + size / 2 - 0.5), (b0 + size / 2 + 0.5, b1)]
            for lo, hi in spans:
                mid, half = (lo + hi) / 2, (hi - lo) / 2 + 0.05
                a = i * size
                for pos, sz in ((f"{mid} {a} 1.25", f"{half} 0.05 1.25"), (f"{a} {mid} 1.25", f"0.05 {half} 1.25")):
                    out.append(f'<geom type="box" pos="{pos}" size="{sz}" rgba="0.9 0.9 0.85 1"/>')
                    nb += 1
    k_f = 0
    while nb < n_boxes - 4:
        x, y = rng.uniform(0.8, L - 0.8, 2)
        yaw = rng.choice([0.0, 90.0, rng.uniform(0, 180)])
        w, dpt, h = rng.uniform(0.3, 0.8), rng.uniform(0.2, 0.5), rng.uniform(0.4, 1.0)
        parts = [(0, 0, h, w, dpt, 0.02)] + [(sx * (w - 0.03), sy * (dpt - 0.03), h / 2, 0.03, 0.03, h / 2)
                                             for sx in (-1, 1) for sy in (-1, 1)]
        out.append(f'<body name="furniture:table:{k_f}" pos="{x:.3f} {y:.3f} 0" euler="0 0 {yaw:.1f}">')
        for px, py, pz, hx, hy, hz in parts:
            out.append(f'<geom type="box" pos="{px:.3f} {py:.3f} {pz:.3f}" size="{hx:.3f} {hy:.3f} {hz:.3f}" '
                       f'rgba="0.5 0.35 0.2 1"/>')
        out.append('</body>')
        nb += len(parts)
        k_f += 1
    for k in range(4):
        out.append(f'<body name="object:apple:{k}" mocap="true" pos="{k} 0 -5"><geom type="sphere" '
                   f'size="0.045" rgba="0.8 0.1 0.1 1"/></body>')
    out.append("</worldbody></mujoco>")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# env benchmark

def _free_poses(sim, n: int, rng: np.random.Generator) -> np.ndarray:
    """n random (x, y, yaw) where the agent's capsule touches no blocker (native collision check)."""
    import mujoco
    m = sim.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    floor = [g for g in range(sim.scene_ngeom) if g not in set(sim.blockers)]
    pts = d.geom_xpos[floor if floor else list(range(sim.scene_ngeom)), :2]
    lo, hi = pts.min(0), pts.max(0)
    out = []
    while len(out) < n:
        d.qpos[sim.qpos_adr] = [*rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi)]
        mujoco.mj_fwdPosition(m, d)
        if d.ncon == 0:
            out.append(d.qpos[sim.qpos_adr].copy())
    return np.asarray(out, np.float32)


def _time_calls(fn, args_seq, repeats: int) -> float:
    """Best-of-`repeats` mean seconds per call over args_seq (results blocked at the end)."""
    import jax
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        out = None
        for a in args_seq:
            out = fn(*a)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - t) / len(args_seq))
    return best


class _Native:
    """The same env step in native MuJoCo: substeps x mj_step + brake + mj_multiRay + lookups."""

    def __init__(self, sim, cam, poses: np.ndarray):
        import mujoco
        from . import sensors as SN
        from . import sim as S
        self.mujoco, self.sim, self.cam = mujoco, sim, cam
        self.m = sim.mj_model
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
        delta = [np.array([c, s, 0]) * self.fwd, -np.array([c, s, 0]) * self.fwd,
                 np.array([0, 0, self.turn]), np.array([0, 0, -self.turn]), np.zeros(3)][action]
        for cn in self.ctrl:
            d.ctrl[:] = delta * cn
            mj.mj_step(self.m, d)
        d.qvel[self.sim.dof_adr] = 0.0

    def render(self, d):
        cfg = self.cam.config
        x, y, yaw = d.qpos[self.sim.qpos_adr]
        p = np.radians(cfg.pitch_deg)
        cy, sy = np.cos(yaw), np.sin(yaw)
        rot = np.stack([[sy, -cy, 0.0], [-cy * np.sin(p), -sy * np.sin(p), np.cos(p)],
                        [cy * np.cos(p), sy * np.cos(p), np.sin(p)]], 1)
        o = np.array([x + cfg.forward_offset * cy, y + cfg.forward_offset * sy, cfg.mount_height])
        vec = (self.dirs_cam @ rot.T).ravel()
        self.mujoco.mj_multiRay(self.m, d, o, vec, None, 1, self.sim.agent_body, self.gid, self.dist,
                                None, self.nray, cfg.max_depth)
        hit = (self.gid >= 0) & (self.dist <= cfg.max_depth)
        g = np.where(hit, self.gid, 0)
        depth = np.where(hit, self.dist, cfg.max_depth)
        return depth, np.where(hit, self.inst[g], -1), np.where(hit, self.cls[g], 0), self.rgb[g]

    def time(self, actions: np.ndarray, what: str, repeats: int) -> float:
        """Best seconds per env step over the (T, B) actions."""
        best = np.inf
        for _ in range(repeats):
            t = time.perf_counter()
            for row in actions:
                for d, a in zip(self.datas, row):
                    if what in ("physics", "env"):
                        self.physics(d, int(a))
                    if what in ("render", "env"):
                        self.render(d)
            best = min(best, (time.perf_counter() - t) / actions.size)
        return best


def bench_env(scene_path: str | None, num_envs=(1, 16, 64), steps: int = 20, repeats: int = 3,
              width: int = 32, height: int = 32, backends=("kernel", "kernel-nocull", "mjx"),
              native_envs: int = 8, seed: int = 0, log=print) -> list[dict]:
    import jax
    import jax.numpy as jnp

    from . import sensors as SN
    from .sim import Simulator

    if scene_path:
        sim = Simulator.from_file(scene_path)
        try:
            from .scenes import load_scene
            scene = load_scene(scene_path)
        except Exception:  # unannotated file: generic tables
            scene = None
    else:
        sim = Simulator.from_xml(synthetic_house_xml())
        scene = None
    m = sim.mj_model
    log(f"scene: {scene_path or 'synthetic_house_xml()'}: {m.ngeom} geoms "
        f"({np.bincount(m.geom_type, minlength=7)[[6, 2, 3]].tolist()} box/sphere/capsule), "
        f"{len(sim.blockers)} blockers, MJX max_geom_pairs K={sim.max_geom_pairs}, "
        f"{sim.config.substeps} substeps/step")
    rng = np.random.default_rng(seed)
    base = SN.CameraConfig(width=width, height=height)
    n_box = int((m.geom_type == 6).sum())
    cams = {}
    for b in backends:
        if b == "kernel":
            cfg = base
        elif b == "kernel-nocull":
            cfg = dataclasses.replace(base, k_box=n_box, k_sphere=m.ngeom, k_capsule=m.ngeom)
        elif b == "mjx":
            cfg = dataclasses.replace(base, backend="mjx")
        else:
            raise ValueError(f"unknown backend {b!r}")
        cams[b] = SN.Camera.for_simulator(sim, cfg, scene=scene)
    log(f"camera: {width}x{height}, vfov {base.vfov_deg} deg, max_depth {base.max_depth} m, "
        f"k_box {base.k_box}")

    rows = []
    phys = jax.jit(jax.vmap(sim.step))
    init = jax.jit(jax.vmap(sim.init))
    pose_fn = jax.jit(jax.vmap(sim.agent_pose))
    for B in num_envs:
        poses = _free_poses(sim, B, rng)
        acts = rng.integers(0, 5, size=(steps, B)).astype(np.int32)
        d0 = init(jnp.asarray(poses))
        t = time.perf_counter()
        d1 = phys(d0, jnp.asarray(acts[0]))
        jax.block_until_ready(d1)
        log(f"B={B}: physics compile {time.perf_counter() - t:.1f} s")

        # physics: a chain of steps (each call consumes the previous data)
        def run_phys(d):
            for a in acts:
                d = phys(d, jnp.asarray(a))
            return d
        best = np.inf
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(run_phys(d0))
            best = min(best, (time.perf_counter() - t) / steps)
        t_phys = best
        rows.append(dict(num_envs=B, what="physics (MJX)", s_per_batch=t_phys))
        d_end = run_phys(d0)
        p_end = pose_fn(d_end)

        for b, cam in cams.items():
            rend = jax.jit(jax.vmap(cam.render))
            t = time.perf_counter()
            out = rend(d_end, p_end)
            jax.block_until_ready(out)
            log(f"B={B}: render/{b} compile {time.perf_counter() - t:.1f} s, "
                f"uncertain rays {int(np.asarray(out.uncertain).sum())}")
            t_r = _time_calls(rend, [(d_end, p_end)] * steps, repeats)
            rows.append(dict(num_envs=B, what=f"render/{b}", s_per_batch=t_r))

            def run_env(d):
                for a in acts:
                    d = phys(d, jnp.asarray(a))
                    o = rend(d, pose_fn(d))
                return d, o
            best = np.inf
            for _ in range(repeats):
                t = time.perf_counter()
                jax.block_until_ready(run_env(d0))
                best = min(best, (time.perf_counter() - t) / steps)
            rows.append(dict(num_envs=B, what=f"env/{b}", s_per_batch=best))

    # native MuJoCo reference (single core, Python loop over envs)
    nat = _Native(sim, cams[backends[0]], _free_poses(sim, native_envs, rng))
    acts = rng.integers(0, 5, size=(max(steps // 2, 2), native_envs))
    nat_t = {w: nat.time(acts, w, repeats) for w in ("physics", "render", "env")}
    for r in rows:
        r["steps_per_s"] = r["num_envs"] / r["s_per_batch"]
        kind = r["what"].split("/")[0].split(" ")[0]
        r["native_steps_per_s"] = 1.0 / nat_t[kind]
        r["ratio"] = r["steps_per_s"] / r["native_steps_per_s"]
    rows.append(dict(num_envs=native_envs, what="native physics (mj_step loop)", s_per_batch=nat_t["physics"] * native_envs,
                     steps_per_s=1 / nat_t["physics"], native_steps_per_s=1 / nat_t["physics"], ratio=1.0))
    rows.append(dict(num_envs=native_envs, what="native render (mj_multiRay)", s_per_batch=nat_t["render"] * native_envs,
                     steps_per_s=1 / nat_t["render"], native_steps_per_s=1 / nat_t["render"], ratio=1.0))
    rows.append(dict(num_envs=native_envs, what="native env", s_per_batch=nat_t["env"] * native_envs,
                     steps_per_s=1 / nat_t["env"], native_steps_per_s=1 / nat_t["env"], ratio=1.0))
    return rows


def format_env_rows(rows: list[dict]) -> str:
    lines = ["| num_envs | what | ms / batch step | env steps / s | native steps / s | ratio |",
             "| ---: | --- | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['num_envs']} | {r['what']} | {1e3 * r['s_per_batch']:.1f} | "
                     f"{r['steps_per_s']:.0f} | {r['native_steps_per_s']:.0f} | {r['ratio']:.2f} |")
    return "\n".join(lines)


def _add_env_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default=_DEFAULT_SCENE if os.path.exists(_DEFAULT_SCENE) else None,
                   help="scene file (default scenes/house.xml); 'synthetic' for a ~300-box house")
    p.add_argument("--num-envs", type=int, nargs="+", default=[1, 16, 64])
    p.add_argument("--steps", type=int, default=20, help="timed calls per measurement")
    p.add_argument("--repeats", type=int, default=3, help="best of this many timed runs")
    p.add_argument("--width", type=int, default=32)
    p.add_argument("--height", type=int, default=32)
    p.add_argument("--backends", nargs="+", default=["kernel", "kernel-nocull", "mjx"],
                   choices=["kernel", "kernel-nocull", "mjx"])
    p.add_argument("--native-envs", type=int, default=8)


def _run_env(a: argparse.Namespace) -> None:
    print(machine_info())
    scene = None if a.scene in (None, "synthetic") else a.scene
    rows = bench_env(scene, tuple(a.num_envs), a.steps, a.repeats, a.width, a.height,
                     tuple(a.backends), a.native_envs)
    print(format_env_rows(rows))
    if hasattr(os, "getloadavg"):
        print("load avg at the end: %.1f %.1f %.1f" % os.getloadavg())


def _add_graph_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("rest", nargs=argparse.REMAINDER, help="arguments of hron_jax.bench_graph")


def _run_graph(a: argparse.Namespace) -> None:
    from . import bench_graph
    bench_graph.main(a.rest)


# ---------------------------------------------------------------------------------------------
# model benchmark: forward and forward+grad of every actor-critic variant on house graphs

def model_inputs(batch: int = 64, scene_path: str = _DEFAULT_SCENE, image: int = 32, seed: int = 0):
    """A batch of observations following hron_jax.models' contract: scene graphs of `scene_path`
    from GraphBuilder with every node discovered and every pool object placed in a random slot
    (house.xml: N=71, E=194), random poses, random RGB-D / map images, random goals."""
    import jax
    import jax.numpy as jnp

    from . import goals as GL
    from .graph_builder import GraphBuilder, GraphConfig, Placement
    from .scenes import load_scene
    from .scenes import vocabulary as V

    rng = np.random.default_rng(seed)
    scene = load_scene(scene_path)
    gb = GraphBuilder(scene, GraphConfig())
    o0 = scene.num_rooms + scene.num_furniture
    half = V.OBJECT_HALF[scene.vocab_index[o0:]]
    slot = rng.integers(scene.num_slots, size=(batch, scene.num_objects))
    support = scene.slot_center[:, 2] - scene.slot_half[:, 2]
    pos = np.concatenate([scene.slot_center[slot, :2], (support[slot] + half[None, :, 2])[..., None]], -1)
    placement = Placement(active=jnp.ones((batch, scene.num_objects), bool),
                          pos=jnp.asarray(pos, jnp.float32),
                          furniture=jnp.asarray(scene.slot_furniture[slot], jnp.int32),
                          relation=jnp.asarray(scene.slot_relation[slot], jnp.int32))
    lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
    poses = jnp.asarray(np.concatenate([rng.uniform(lo, hi, (batch, 2)),
                                        rng.uniform(-np.pi, np.pi, (batch, 1))], -1), jnp.float32)
    disc = jnp.broadcast_to(gb.real, (batch, gb.max_nodes))
    graph = jax.jit(jax.vmap(gb.graph))(disc, placement, poses)
    cat = np.asarray(graph.nodes["category"])
    pick = rng.integers(0, gb.max_nodes, (batch, 3))
    goal = np.zeros((batch, GL.GOAL_DIM), np.float32)
    goal[np.arange(batch)[:, None], rng.integers(0, GL.GOAL_DIM, (batch, 3))] = 1.0
    obs = dict(graph=graph, goal=jnp.asarray(goal),
               goal_classes=jnp.asarray(np.take_along_axis(cat, pick, 1), jnp.int32),
               rgbd=jnp.asarray(rng.random((batch, image, image, 4)), jnp.float32),
               map=jnp.asarray(rng.random((batch, image, image, 3)), jnp.float32))
    return obs, gb


def bench_model(variants=("rgbd", "rgbd_mm", "rgbd_sg", "rgbd_sg_attn", "gcn", "yang"),
                batch: int = 64, reps: int = 20, scene_path: str = _DEFAULT_SCENE, seed: int = 0,
                log=print) -> list[dict]:
    """Rows {variant, fwd_ms, grad_ms, fwd_cpu_ms, grad_cpu_ms, compile_s} at `batch`.

    fwd = jit(model.apply); grad = jit(value_and_grad) of a PPO-like scalar (log-prob of action 0
    + squared value) w.r.t. all parameters. Parameters are scaled normals (timing does not depend
    on them; flax init would cost ~10 s of compile per variant). The variants are timed round
    robin, one call each per round, and the median over `reps` rounds is reported, so a load change
    on a shared machine hits every variant alike; *_cpu_ms is the process CPU time per call (all
    threads), steadier than wall time when other jobs share the cores.

    Allocator: XLA:CPU takes each call's temporaries from malloc, and glibc returns large blocks
    to the OS, so every call page-faults its whole working set again (measured ~0.45 ms per MB on
    the 2-core VM: 30-50 % of rgbd_sg_attn's gradient time). `main` (like train.py and eval.py)
    calls hron_jax.training.tune_malloc() first, which keeps that memory in the process.
    """
    import jax
    import jax.numpy as jnp

    from .models import make_model

    obs, gb = model_inputs(batch, scene_path, seed=seed)
    log(f"batch {batch}: N={gb.max_nodes} nodes, E={gb.max_edges} edges "
        f"(live {int(np.asarray(obs['graph'].edges['mask']).sum()) / batch:.0f}/graph)")
    one = jax.tree.map(lambda a: a[0], obs)
    fns = {}
    for name in variants:
        model = make_model(name, 5)
        shapes = jax.eval_shape(model.init, jax.random.PRNGKey(0), one)
        r = np.random.default_rng(seed)
        variables = jax.tree.map(lambda s: jnp.asarray(
            r.standard_normal(s.shape) / np.sqrt(max(int(np.prod(s.shape[:-1])), 1)), s.dtype), shapes)

        def loss(v, o, model=model):
            logits, value = model.apply(v, o)
            return jnp.sum(jax.nn.log_softmax(logits)[:, 0]) + jnp.sum(value ** 2)

        fwd, grad = jax.jit(model.apply), jax.jit(jax.value_and_grad(loss))
        t = time.perf_counter()
        jax.block_until_ready(fwd(variables, obs))
        jax.block_until_ready(grad(variables, obs))
        fns[name] = (fwd, grad, variables, time.perf_counter() - t)
    times = {name: ([], [], [], []) for name in variants}
    for _ in range(reps):
        for name, (fwd, grad, v, _) in fns.items():
            for i, f in enumerate((fwd, grad)):
                c, t = time.process_time(), time.perf_counter()
                jax.block_until_ready(f(v, obs))
                times[name][i].append(time.perf_counter() - t)
                times[name][2 + i].append(time.process_time() - c)
    med = lambda name, i: 1e3 * float(np.median(times[name][i]))  # noqa: E731
    return [dict(variant=name, fwd_ms=med(name, 0), grad_ms=med(name, 1), fwd_cpu_ms=med(name, 2),
                 grad_cpu_ms=med(name, 3), compile_s=fns[name][3]) for name in variants]


def format_model_rows(rows: list[dict], batch: int) -> str:
    ref = {r["variant"]: r for r in rows}.get("gcn")
    lines = [f"| variant | forward ms (B={batch}) | fwd+grad ms (B={batch}) | fwd / gcn | grad / gcn "
             "| fwd CPU-ms | fwd+grad CPU-ms | compile s |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        rel = (f"{r['fwd_ms'] / ref['fwd_ms']:.2f} | {r['grad_ms'] / ref['grad_ms']:.2f}" if ref
               else "- | -")
        lines.append(f"| {r['variant']} | {r['fwd_ms']:.1f} | {r['grad_ms']:.1f} | {rel} | "
                     f"{r['fwd_cpu_ms']:.0f} | {r['grad_cpu_ms']:.0f} | {r['compile_s']:.1f} |")
    return "\n".join(lines)


def _add_model_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--variants", nargs="+",
                   default=["rgbd", "rgbd_mm", "rgbd_sg", "rgbd_sg_attn", "gcn", "yang"])
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--reps", type=int, default=20, help="timed rounds (median reported)")
    p.add_argument("--scene", default=_DEFAULT_SCENE)


def _run_model(a: argparse.Namespace) -> None:
    print(machine_info())
    rows = bench_model(tuple(a.variants), a.batch, a.reps, a.scene)
    print(format_model_rows(rows, a.batch))
    if hasattr(os, "getloadavg"):
        print("load avg at the end: %.1f %.1f %.1f" % os.getloadavg())


# ---------------------------------------------------------------------------------------------
# train benchmark

def bench_train(task: str = "exploratory", model: str = "rgbd_sg_attn", num_envs=(16, 64, 256),
                num_steps: int = 8, minibatch_size: int = 128, epochs: int | None = None,
                repeats: int = 2, extra: dict | None = None, log=print) -> list[dict]:
    """Env steps/s of one PPO update of the program train.py runs (hron_jax.training, one seed),
    for each num_envs: a rollout of num_steps steps of num_envs envs plus `epochs` epochs over
    minibatches of ~minibatch_size samples (the paper's 128); and of the rollout alone
    (PPO.evaluate with the sampled policy: env + policy forward), so the update's share shows.
    Times: best of `repeats` calls after compilation. extra: more train.py options (dest names)."""
    import jax

    from . import training as T

    rows = []
    for B in num_envs:
        batch = B * num_steps
        args = dict(task=task, model=model, num_envs=B, num_steps=num_steps, total_steps=batch,
                    minibatches=max(1, batch // minibatch_size), **(extra or {}))
        if epochs is not None:
            args["epochs"] = epochs
        cfg = T.config_from_args(args)
        t = time.perf_counter()
        prog = T.programs(cfg)
        runner = prog.initialize(T.seed_keys(cfg))
        jax.block_until_ready(runner)
        t_init = time.perf_counter() - t
        fn, t_compile = prog.compiled_chunk(1)
        best = np.inf
        for _ in range(repeats):
            t = time.perf_counter()
            runner, m = fn(runner)
            jax.block_until_ready((runner, m))
            best = min(best, time.perf_counter() - t)
        params = jax.tree.map(lambda x: x[0], runner.params)
        ev = jax.jit(prog.ppo.evaluate, static_argnums=(2, 3))
        t = time.perf_counter()
        jax.block_until_ready(ev(params, jax.random.PRNGKey(1), num_steps, False))
        t_ev_compile = time.perf_counter() - t
        best_ev = np.inf
        for i in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(ev(params, jax.random.PRNGKey(2 + i), num_steps, False))
            best_ev = min(best_ev, time.perf_counter() - t)
        row = dict(num_envs=B, minibatches=cfg.ppo.num_minibatches, epochs=cfg.ppo.update_epochs,
                   compile_s=t_init + t_compile + t_ev_compile, s_per_update=best,
                   train_steps_per_s=batch / best, rollout_steps_per_s=batch / best_ev,
                   update_share=max(0.0, 1.0 - best_ev / best))
        log(f"B={B}: init {t_init:.1f} s, compile {t_compile:.1f} s, {batch / best:.0f} train steps/s")
        rows.append(row)
    return rows


def format_train_rows(rows: list[dict]) -> str:
    lines = ["| num_envs | minibatches x epochs | compile s | s / update | train env steps / s | "
             "rollout-only steps / s | update share |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['num_envs']} | {r['minibatches']} x {r['epochs']} | {r['compile_s']:.0f} | "
                     f"{r['s_per_update']:.3f} | {r['train_steps_per_s']:.0f} | "
                     f"{r['rollout_steps_per_s']:.0f} | {100 * r['update_share']:.0f}% |")
    return "\n".join(lines)


def _add_train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", default="exploratory", choices=("choice", "directed", "exploratory"))
    p.add_argument("--model", default="rgbd_sg_attn")
    p.add_argument("--num-envs", type=int, nargs="+", default=[16, 64, 256])
    p.add_argument("--num-steps", type=int, default=8, help="rollout length per update")
    p.add_argument("--minibatch-size", type=int, default=128)
    p.add_argument("--epochs", type=int, default=None, help="default: the task's PPO default")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--distractors", action="store_true")


def _run_train(a: argparse.Namespace) -> None:
    print(machine_info())
    extra = {"distractors": True} if a.distractors else {}
    rows = bench_train(a.task, a.model, tuple(a.num_envs), a.num_steps, a.minibatch_size, a.epochs,
                       a.repeats, extra)
    print(f"task {a.task}, model {a.model}, num_steps {a.num_steps}, minibatch ~{a.minibatch_size}")
    print(format_train_rows(rows))
    if hasattr(os, "getloadavg"):
        print("load avg at the end: %.1f %.1f %.1f" % os.getloadavg())


# ---------------------------------------------------------------------------------------------
# conv benchmark: why the image encoder uses PatchConv

def bench_conv(batch: int = 128, size: int = 32, steps: int = 8, repeats: int = 3) -> list[dict]:
    """ms per fwd+grad step of the RGB-D conv stack (3 layers of ModelConfig's defaults) on
    f32[batch, size, size, 4], with flax nn.Conv (XLA convolution) and with encoders.PatchConv,
    each run as PPO runs minibatches (`steps` SGD steps in one lax.scan) and unrolled (the same
    steps as straight-line code). XLA:CPU emits the convolution's gradient inside a while loop
    ~30x slower than outside it; PatchConv's slices + matmul do not depend on the loop."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    from .models.config import ModelConfig
    from .models.encoders import RELU_INIT, PatchConv

    cfg = ModelConfig()
    layers = list(zip(cfg.conv_features, cfg.conv_kernels, cfg.conv_strides))

    class Stack(nn.Module):
        patch: bool

        @nn.compact
        def __call__(self, x):
            for f, k, s in layers:
                conv = (PatchConv(f, k, s) if self.patch else
                        nn.Conv(f, (k, k), (s, s), padding="SAME", kernel_init=RELU_INIT))
                x = nn.relu(conv(x))
            return x

    x = jax.random.normal(jax.random.PRNGKey(0), (steps, batch, size, size, 4))
    rows = []
    for name, patch in (("nn.Conv (XLA convolution)", False), ("PatchConv (slices + matmul)", True)):
        model = Stack(patch)
        params = model.init(jax.random.PRNGKey(1), x[0])
        loss = lambda p, xb: jnp.sum(model.apply(p, xb) ** 2)  # noqa: E731

        def sgd(p, xs, unroll):
            def body(p, xb):
                g = jax.grad(loss)(p, xb)
                return jax.tree.map(lambda a, b: a - 1e-6 * b, p, g), None
            return jax.lax.scan(body, p, xs, unroll=unroll)[0]

        row = dict(conv=name)
        for label, unroll in (("scan", 1), ("unrolled", steps)):
            fn = jax.jit(lambda p, xs, u=unroll: sgd(p, xs, u))
            jax.block_until_ready(fn(params, x))
            row[label] = 1e3 * _time_calls(fn, [(params, x)], repeats) / steps
        rows.append(row)
    return rows


def _add_conv_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batch", type=int, default=128, help="minibatch (PPO: 128)")
    p.add_argument("--size", type=int, default=32, help="image side")
    p.add_argument("--steps", type=int, default=8, help="SGD steps per call")
    p.add_argument("--repeats", type=int, default=3)


def _run_conv(a: argparse.Namespace) -> None:
    print(machine_info())
    rows = bench_conv(a.batch, a.size, a.steps, a.repeats)
    print(f"RGB-D conv stack fwd+grad, batch {a.batch}, {a.size}x{a.size}x4, {a.steps} steps per call")
    print("| conv | ms / step in lax.scan | ms / step unrolled |\n| --- | ---: | ---: |")
    for r in rows:
        print(f"| {r['conv']} | {r['scan']:.1f} | {r['unrolled']:.1f} |")


_SUBCOMMANDS = {
    "env": (_add_env_args, _run_env, "simulator + camera env steps/s vs native MuJoCo"),
    "graph": (_add_graph_args, _run_graph, "scene-graph / metric-map update cost"),
    "model": (_add_model_args, _run_model, "actor-critic forward / forward+grad ms per variant"),
    "train": (_add_train_args, _run_train, "PPO train env steps/s (env + update) per num_envs"),
    "conv": (_add_conv_args, _run_conv, "conv encoder fwd+grad in lax.scan: nn.Conv vs PatchConv"),
}


def main(argv=None) -> None:
    from .training import tune_malloc
    tune_malloc()
    parser = argparse.ArgumentParser(prog="python -m hron_jax.bench", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    for name, (add, _, helptext) in _SUBCOMMANDS.items():
        add(sub.add_parser(name, help=helptext))
    a = parser.parse_args(argv)
    _SUBCOMMANDS[a.cmd][1](a)


if __name__ == "__main__":
    main()
