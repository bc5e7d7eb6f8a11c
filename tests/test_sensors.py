"""Camera: analytic depth on box scenes, segmentation ids, agreement with MuJoCo's native mj_ray
(random boxes / spheres / capsules, random poses and pitch; the house with the default K), the
culling certificate, the mjx.ray backend, vmap, and the simulator integration (agent excluded).
CPU; the sensor tests need no MJX physics compile (geom poses come from native kinematics)."""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hron_jax import sensors as SN
from hron_jax.paths import REPO_ROOT

ROOT = REPO_ROOT
HOUSE = os.path.join(ROOT, "scenes", "house.xml")
BOX_ROOM = os.path.join(ROOT, "tests", "scenes", "box_room.xml")

# A huge wall whose face is at x = 3 (fills any view facing +x), a box in front of it spanning
# x in [2, 2.5], y in [0.5, 1.5], z in [0, 2], a sphere and a capsule at known places.
KNOWN = """
<mujoco>
  <asset><material name="plain"/></asset>
  <worldbody>
    <geom name="wall" type="box" pos="3.05 0 0" size="0.05 100 100" rgba="0.5 0.6 0.7 1"/>
    <geom name="box" type="box" pos="2.25 1.0 1.0" size="0.25 0.5 1.0" rgba="1 0 0 1"/>
    <geom name="ball" type="sphere" pos="2.0 -1.0 1.0" size="0.3" rgba="0 1 0 1"/>
    <geom name="pill" type="capsule" pos="2.0 -0.2 1.0" size="0.1 0.3" rgba="0 0 1 1"/>
    <geom name="ghost" type="box" pos="1.0 0 1.0" size="0.1 0.1 0.1" rgba="1 1 1 0"/>
  </worldbody>
</mujoco>
"""


def _model_data(xml=None, path=None):
    m = mujoco.MjModel.from_xml_path(path) if path else mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    return m, d


def _render(cam, d, pose):
    # One frame of a new camera per call: a fresh jit of its bound method compiles each time (~1 s),
    # still cheaper than the eager kernel; frames of one camera in a loop use a fixture's jit.
    return jax.jit(cam.render_geoms)(
        jnp.asarray(d.geom_xpos, jnp.float32),
        jnp.asarray(d.geom_xmat, jnp.float32),
        jnp.asarray(pose, jnp.float32),
    )


class RayRef:
    """Native reference image: mj_ray per pixel on the same rays (depth, misses = inf, geom id)."""

    def __init__(self, m, d, cfg, pose, exclude_body=-1):
        o, dirs = SN.world_rays(jnp.asarray(pose, jnp.float32), cfg)
        self.m, self.d, self.cfg = m, d, cfg
        self.o = np.asarray(o, np.float64)
        self.dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
        gid = np.zeros(1, np.int32)
        t = np.full(len(self.dirs), np.inf)
        g = np.full(len(self.dirs), -1)
        for i, v in enumerate(self.dirs):
            x = mujoco.mj_ray(m, d, self.o, v, None, 1, exclude_body, gid)
            if x >= 0:
                t[i], g[i] = x, gid[0]
        self.t = t.reshape(cfg.height, cfg.width)
        self.g = g.reshape(cfg.height, cfg.width)

    def geom_distance(self, pixel, g):
        """mju_rayGeom: distance along pixel's ray to geom g alone (-1 if missed)."""
        m, d = self.m, self.d
        v = self.dirs[pixel[0] * self.cfg.width + pixel[1]]
        return mujoco.mju_rayGeom(
            d.geom_xpos[g], d.geom_xmat[g], m.geom_size[g], self.o, v, int(m.geom_type[g])
        )

    def check(self, out, tol=1e-4):
        """Depth equal to mj_ray's within tol everywhere; the same geom wherever mj_ray hit one,
        except where two surfaces coincide (then the reported geom must be hit at that depth)."""
        cfg = self.cfg
        hit = self.t <= cfg.max_depth
        depth, geom = np.asarray(out.depth), np.asarray(out.geom)
        np.testing.assert_allclose(depth, np.where(hit, self.t, cfg.max_depth), atol=tol, rtol=0)
        for px in np.argwhere(geom != np.where(hit, self.g, -1)):
            g = int(geom[tuple(px)])
            assert g >= 0 and abs(self.geom_distance(px, g) - self.t[tuple(px)]) < tol, (px, g)


# ------------------------------------------------------------------ analytic scenes


@pytest.fixture(scope="module")
def known():
    m, d = _model_data(KNOWN)
    cfg = SN.CameraConfig(width=64, height=16, vfov_deg=40.0, max_depth=20.0, mount_height=1.0)
    inst = np.full(m.ngeom, -1, np.int32)
    cls = np.ones(m.ngeom, np.int32)
    inst[m.geom("box").id], cls[m.geom("box").id] = 7, 23
    inst[m.geom("ball").id], cls[m.geom("ball").id] = 9, 40
    inst[m.geom("pill").id], cls[m.geom("pill").id] = 11, 41
    cam = SN.Camera(m, cfg, inst, cls)
    return m, d, cfg, cam, jax.jit(cam.render_geoms)


def _known_render(known, pose):
    m, d, cfg, cam, fn = known
    return fn(
        jnp.asarray(d.geom_xpos, jnp.float32),
        jnp.asarray(d.geom_xmat, jnp.float32),
        jnp.asarray(pose, jnp.float32),
    )


def test_wall_depth_is_analytic_zdepth(known):
    """Facing the wall from x0 with the box etc. behind: every pixel's z-depth is 3 - x0."""
    for x0 in (2.6, 2.9):
        out = _known_render(known, [x0, 0.0, 0.0])
        np.testing.assert_allclose(np.asarray(out.depth), 3.0 - x0, atol=1e-5)
        assert np.all(np.asarray(out.instance) == -1) and np.all(np.asarray(out.semantic) == 1)
        assert int(out.uncertain) == 0
    # turned by 30 degrees the z-depth of the plane still is the same for every pixel of a row...
    out = _known_render(known, [2.6, 0.0, math.radians(30)])
    dep = np.asarray(out.depth)
    # ...and follows the plane equation: x0 + t (cos30 + X sin30) = 3  with X = -(world y slope)
    xs = (2.0 * (np.arange(64) + 0.5) / 64 - 1.0) * known[2].tan_h
    expect = 0.4 / (math.cos(math.radians(30)) + xs * math.sin(math.radians(30)))
    np.testing.assert_allclose(dep, np.broadcast_to(expect, dep.shape), rtol=1e-5)


def test_box_front_and_side_at_known_columns(known):
    """From the origin facing +x: the box's front face (x = 2) shows at depth 2 in the columns whose
    slope X = x_j tan_h lies in [-0.75, -0.25] (world y = -X z), its side face (y = 0.5) at depth
    0.5 / -X in the columns with X in (-0.25, -0.2); RGB is red there, shaded by the normal."""
    m, d, cfg, cam, fn = known
    out = _known_render(known, [0.0, 0.0, 0.0])
    dep, inst, rgb = np.asarray(out.depth), np.asarray(out.instance), np.asarray(out.rgb)
    X = (2.0 * (np.arange(cfg.width) + 0.5) / cfg.width - 1.0) * cfg.tan_h
    mid = cfg.height // 2  # a row near the horizon: camera height 1 is inside the box's z range
    front = (X >= -0.75 + 1e-6) & (X <= -0.25 - 1e-6)
    side = (X > -0.25 + 1e-6) & (X < -0.2 - 1e-6)
    assert front.sum() >= 8 and side.sum() >= 1
    np.testing.assert_allclose(dep[mid, front], 2.0, atol=1e-5)
    np.testing.assert_allclose(dep[mid, side], 0.5 / -X[side], atol=1e-5)
    assert np.all(inst[mid, front | side] == 7)
    # front face faces the camera (bright), side face is grazing (darker); both red only
    assert np.all(rgb[mid, front, 1:] == 0) and np.all(rgb[mid, front, 0] > rgb[mid, side, 0].max())
    # left of the box (X < -0.75) the wall shows at depth 3
    np.testing.assert_allclose(dep[mid, X < -0.75 - 1e-6], 3.0, atol=1e-5)


def test_segmentation_ids_and_misses(known):
    m, d, cfg, cam, fn = known
    out = _known_render(known, [0.0, 0.0, 0.0])
    X = (2.0 * (np.arange(cfg.width) + 0.5) / cfg.width - 1.0) * cfg.tan_h
    mid = cfg.height // 2
    col = lambda y_world, z: int(np.argmin(np.abs(X - (-y_world / z))))  # noqa: E731
    inst, sem, geom = np.asarray(out.instance), np.asarray(out.semantic), np.asarray(out.geom)
    assert (inst[mid, col(1.0, 2.0)], sem[mid, col(1.0, 2.0)]) == (7, 23)  # box
    assert (inst[mid, col(-1.0, 1.7)], sem[mid, col(-1.0, 1.7)]) == (9, 40)  # sphere front
    assert (inst[mid, col(-0.2, 1.9)], sem[mid, col(-0.2, 1.9)]) == (11, 41)  # capsule
    assert geom[mid, col(-1.0, 1.7)] == m.geom("ball").id
    # the invisible (alpha 0) box straight ahead is skipped, as mj_ray does: the wall is seen
    assert geom[mid, cfg.width // 2] == m.geom("wall").id
    # facing away: nothing at all
    out = _known_render(known, [0.0, 0.0, math.pi])
    assert np.all(np.asarray(out.geom) == -1) and np.all(np.asarray(out.instance) == -1)
    assert np.all(np.asarray(out.semantic) == 0) and np.all(np.asarray(out.rgb) == 0)
    np.testing.assert_allclose(np.asarray(out.depth), cfg.max_depth)


def test_shading_matches_analytic_normals(known):
    """RGB = geom colour x (ambient + (1 - ambient) lambda), lambda = half headlight n . (-d) plus
    half sun n . l (each clipped at 0), with n the outward normal at mj_ray's hit point computed
    here in float64 from the geom's frame (box face, sphere radius, capsule axis distance)."""
    m, d, cfg, cam, _ = known
    pose = [0.0, 0.1, 0.05]
    out = _known_render(known, pose)
    ref = RayRef(m, d, cfg, pose)
    rgba = SN.effective_rgba(m)
    light = np.asarray(cfg.light_dir) / np.linalg.norm(cfg.light_dir)
    checked = set()
    for (i, j), g in np.ndenumerate(ref.g):
        if g < 0 or ref.t[i, j] > cfg.max_depth:
            continue
        v = ref.dirs[i * cfg.width + j]
        rot, size = d.geom_xmat[g].reshape(3, 3), m.geom_size[g]
        q = rot.T @ (ref.o + ref.t[i, j] * v - d.geom_xpos[g])
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            rel = np.abs(q) / size
            top2 = np.sort(rel)[-2:]
            if top2[1] - top2[0] < 1e-3:  # on an edge: the face is ambiguous
                continue
            n = np.eye(3)[np.argmax(rel)] * np.sign(q[np.argmax(rel)])
        elif m.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
            n = q
        else:
            n = q - np.array([0.0, 0.0, np.clip(q[2], -size[1], size[1])])
        n = rot @ (n / np.linalg.norm(n))
        lam = 0.5 * max(0.0, -n @ v / np.linalg.norm(v)) + 0.5 * max(0.0, n @ light)
        want = rgba[g, :3] * (cfg.ambient + (1 - cfg.ambient) * lam)
        np.testing.assert_allclose(np.asarray(out.rgb)[i, j], want, atol=2e-4, err_msg=str((i, j, g)))
        checked.add(int(m.geom_type[g]))
    assert len(checked) == 3  # boxes, the sphere and the capsule were all seen and checked


def test_max_depth_clips_to_miss(known):
    m, d, cfg, cam, fn = known
    cfg2 = dataclasses.replace(cfg, max_depth=2.5)
    cam2 = SN.Camera(m, cfg2, np.asarray(cam.geom_instance), np.asarray(cam.geom_class))
    out = _render(cam2, d, [0.0, 0.0, 0.0])
    dep, geom = np.asarray(out.depth), np.asarray(out.geom)
    assert np.all(dep <= 2.5) and np.all((geom == -1) == (dep == 2.5))
    assert (geom == -1).any() and (geom >= 0).any()


# ------------------------------------------------------------------ agreement with mj_ray


def random_primitives_xml(seed=0, n_box=40, n_sphere=12, n_capsule=12, half=5.0):
    """Boxes, spheres and capsules with random sizes and random 3D orientations over a floor."""
    rng = np.random.default_rng(seed)
    out = [
        '<mujoco><asset><material name="plain"/></asset><worldbody>',
        f'<geom type="box" pos="0 0 -0.05" size="{half + 2} {half + 2} 0.05" rgba=".6 .6 .6 1"/>',
    ]
    for kind, n in (("box", n_box), ("sphere", n_sphere), ("capsule", n_capsule)):
        for _ in range(n):
            p = rng.uniform([-half, -half, 0.0], [half, half, 2.5])
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            size = {
                "box": rng.uniform(0.05, 0.8, 3),
                "sphere": rng.uniform(0.05, 0.5, 1),
                "capsule": rng.uniform([0.05, 0.05], [0.3, 0.6]),
            }[kind]
            rgba = " ".join(f"{c:.2f}" for c in rng.uniform(0.2, 1, 3)) + " 1"
            out.append(
                f'<geom type="{kind}" pos="{p[0]:.4f} {p[1]:.4f} {p[2]:.4f}" '
                f'quat="{q[0]:.5f} {q[1]:.5f} {q[2]:.5f} {q[3]:.5f}" '
                f'size="{" ".join(f"{s:.4f}" for s in size)}" rgba="{rgba}"/>'
            )
    out.append("</worldbody></mujoco>")
    return "\n".join(out)


@pytest.fixture(scope="module")
def primitives():
    return _model_data(random_primitives_xml())


@pytest.mark.parametrize("pitch", [0.0, -20.0])
def test_agrees_with_mj_ray_random_primitives(primitives, pitch):
    """Culling active (k_box < 40 boxes): where the certificate says exact, depth and geom equal
    mj_ray's; across poses at least most frames are certified."""
    m, d = primitives
    cfg = SN.CameraConfig(
        width=24,
        height=20,
        vfov_deg=90.0,
        max_depth=12.0,
        mount_height=1.1,
        pitch_deg=pitch,
        k_box=16,
        k_sphere=6,
        k_capsule=6,
    )
    cam = SN.Camera(m, cfg)
    fn = jax.jit(cam.render_geoms)
    rng = np.random.default_rng(1)
    certified = 0
    for _ in range(6):
        pose = [*rng.uniform(-4, 4, 2), rng.uniform(-math.pi, math.pi)]
        out = fn(
            jnp.asarray(d.geom_xpos, jnp.float32),
            jnp.asarray(d.geom_xmat, jnp.float32),
            jnp.asarray(pose, jnp.float32),
        )
        ref = RayRef(m, d, cfg, pose)
        if int(out.uncertain) == 0:
            certified += 1
            ref.check(out)
        else:  # only the flagged rays may differ
            ref = np.where(ref.t <= cfg.max_depth, ref.t, cfg.max_depth)
            wrong = np.abs(np.asarray(out.depth) - ref) > 1e-4
            assert wrong.sum() <= int(out.uncertain)
    assert certified >= 4


def test_certificate_bounds_errors_when_k_too_small(primitives):
    """With K = 2 culling drops needed geoms: every wrong ray is counted in `uncertain`."""
    m, d = primitives
    cfg = SN.CameraConfig(
        width=16, height=16, vfov_deg=90.0, max_depth=12.0, k_box=2, k_sphere=1, k_capsule=1
    )
    cam = SN.Camera(m, cfg)
    fn = jax.jit(cam.render_geoms)
    rng = np.random.default_rng(2)
    total_wrong = 0
    for _ in range(4):
        pose = [*rng.uniform(-4, 4, 2), rng.uniform(-math.pi, math.pi)]
        out = fn(
            jnp.asarray(d.geom_xpos, jnp.float32),
            jnp.asarray(d.geom_xmat, jnp.float32),
            jnp.asarray(pose, jnp.float32),
        )
        ref_t = RayRef(m, d, cfg, pose).t
        ref = np.where(ref_t <= cfg.max_depth, ref_t, cfg.max_depth)
        wrong = int((np.abs(np.asarray(out.depth) - ref) > 1e-4).sum())
        assert wrong <= int(out.uncertain)
        total_wrong += wrong
    assert total_wrong > 0  # the test does exercise dropped candidates


def _tower_xml(cfg, depth=3.0, thick=0.1):
    """One thin box per row band of `cfg`'s image, stacked at x = depth in front of a camera at the
    origin facing +x: box b spans the band's rays at that depth and 0.1 m more, so no ray of another
    band can reach it; a wall at x = 6 behind them, and 10 boxes behind the camera (never seen)."""
    ys = SN.pixel_directions(cfg)[:, 0, 1]
    rows = -(-cfg.height // cfg.row_bands)
    geoms = []
    for b in range(-(-cfg.height // rows)):
        y = ys[b * rows : (b + 1) * rows]
        z_lo, z_hi = depth * y.min() - 0.1, depth * y.max() + 0.1  # camera Y = world z - mount
        zc, hz = cfg.mount_height + (z_lo + z_hi) / 2, (z_hi - z_lo) / 2
        geoms.append(
            f'<geom name="tier{b}" type="box" pos="{depth + thick / 2} 0 {zc}" size="{thick / 2} 3 {hz}"/>'
        )
    geoms.append('<geom name="back" type="box" pos="6.05 0 1" size="0.05 20 20"/>')
    geoms += [f'<geom type="box" pos="{-2 - i} {i - 5} 1" size="0.2 0.2 0.2"/>' for i in range(10)]
    return f"<mujoco><worldbody>{''.join(geoms)}</worldbody></mujoco>"


def test_row_bands_cull_exactly():
    """Per-band culling (CameraConfig.row_bands, k_band): with one candidate per band, every band of
    a column of stacked boxes still sees its own box, exactly as mj_ray (each band's rows can reach
    only its box and the wall behind, and the box comes first); with one band for the whole column,
    the same k_band = 1 cannot hold them and the certificate flags the rays it got wrong."""
    cfg = SN.CameraConfig(width=8, height=16, vfov_deg=90.0, max_depth=12.0, mount_height=1.0)
    cfg = dataclasses.replace(cfg, row_bands=8, k_box=12, k_band=1)
    m, d = _model_data(_tower_xml(cfg))
    pose = [0.0, 0.0, 0.0]
    out = _render(SN.Camera(m, cfg), d, pose)
    assert int(out.uncertain) == 0
    RayRef(m, d, cfg, pose).check(out)
    tiers = [m.geom(f"tier{b}").id for b in range(8)]
    np.testing.assert_array_equal(np.asarray(out.geom), np.repeat(tiers, 2)[:, None] * np.ones((1, 8), int))
    np.testing.assert_allclose(np.asarray(out.depth), 3.0, atol=1e-5)

    one_band = dataclasses.replace(cfg, row_bands=1)
    coarse = _render(SN.Camera(m, one_band), d, pose)
    wrong = int((np.abs(np.asarray(coarse.depth) - 3.0) > 1e-4).sum())
    assert wrong > 0 and wrong <= int(coarse.uncertain)


@pytest.mark.skipif(not os.path.exists(HOUSE), reason="scenes/house.xml not present")
def test_ranked_selection_is_top_k_without_a_sort():
    """CameraConfig.select = 'rank' (no sort: XLA:GPU sorts every top_k of a column's candidates):
    the same candidates in the same order as lax.top_k wherever top_k has a finite value, ties
    going to the lower index; rows with more than 2k finite scores are flagged (lost), and a
    camera of each kind renders the same house frames."""
    rng = np.random.default_rng(5)
    w, g, k = 300, 311, 32
    n = rng.integers(0, 2 * k + 9, w)  # finite scores per row, a few past 2k
    score = np.full((w, g), np.inf, np.float32)
    for i in range(w):
        score[i, rng.choice(g, n[i], replace=False)] = np.round(rng.uniform(0, 3, n[i]), 1)  # ties
    neg, cand, lost = jax.jit(SN._nearest_ranked, static_argnums=1)(jnp.asarray(score), k)
    ref_neg, ref_cand = jax.lax.top_k(-jnp.asarray(score), k)
    lost, ref_neg, ref_cand = np.asarray(lost), np.asarray(ref_neg), np.asarray(ref_cand)
    np.testing.assert_array_equal(lost, n > 2 * k)
    assert 0 < lost.sum() < w
    kept = ~lost
    np.testing.assert_array_equal(np.isfinite(np.asarray(neg))[kept], np.isfinite(ref_neg)[kept])
    real = kept[:, None] & np.isfinite(ref_neg)
    assert real.sum() > 2000 and np.any(ref_neg[real][1:] == ref_neg[real][:-1])  # ties are tested
    np.testing.assert_array_equal(np.asarray(neg)[real], ref_neg[real])
    np.testing.assert_array_equal(np.asarray(cand)[real], ref_cand[real])

    from hron_jax.scenes import load_scene

    scene = load_scene(HOUSE)
    m, d = _model_data(path=HOUSE)
    args = (jnp.asarray(d.geom_xpos, jnp.float32), jnp.asarray(d.geom_xmat, jnp.float32))
    frames = {}
    for select in ("top_k", "rank"):
        cam = SN.Camera(m, SN.CameraConfig(select=select), scene.geom_instance, scene.geom_class)
        fn = jax.jit(jax.vmap(cam.render_geoms, in_axes=(None, None, 0)))
        frames[select] = fn(*args, jnp.asarray(_room_centre_poses(scene)))
    assert np.asarray(frames["top_k"].geom).max() >= 0
    for a, b in zip(frames["top_k"], frames["rank"]):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="select"):
        SN.Camera(m, SN.CameraConfig(select="sort"))


def test_kernels_agree_with_mjx_primitives():
    """The three exact kernels against mjx.ray's per-geom functions on random local rays."""
    from mujoco.mjx._src import ray as mjx_ray

    rng = np.random.default_rng(3)
    p = rng.normal(size=(500, 3)).astype(np.float32) * 2
    v = (-p + rng.normal(size=(500, 3)) * 1.5).astype(np.float32)  # mostly towards the geom
    size = np.abs(rng.normal(size=(500, 3))).astype(np.float32) + 0.1
    ref_box = jax.vmap(mjx_ray._ray_box)(size, p, v)
    ref_sph = jax.vmap(mjx_ray._ray_sphere)(size, p, v)
    ref_cap = jax.vmap(mjx_ray._ray_capsule)(size, p, v)
    np.testing.assert_allclose(SN.ray_box(size, p, v), ref_box, rtol=1e-4)
    np.testing.assert_allclose(SN.ray_sphere(size[:, 0], p, v), ref_sph, rtol=1e-4)
    np.testing.assert_allclose(SN.ray_capsule(size[:, 0], size[:, 1], p, v), ref_cap, rtol=1e-4)
    assert np.isfinite(ref_box).sum() > 100 and np.isfinite(ref_cap).sum() > 100
    assert (~np.isfinite(ref_box)).sum() > 100


def test_mjx_backend_matches_kernel(primitives):
    m, d = primitives
    from mujoco import mjx

    cfg = SN.CameraConfig(width=12, height=10, vfov_deg=90.0, max_depth=12.0)
    mx = mjx.put_model(m)
    dx = mjx.put_data(m, d)
    pose = jnp.asarray([0.5, -0.5, 0.3], jnp.float32)
    k = jax.jit(SN.Camera(m, cfg).render)(dx, pose)
    r = jax.jit(SN.Camera(m, dataclasses.replace(cfg, backend="mjx"), mjx_model=mx).render)(dx, pose)
    np.testing.assert_allclose(np.asarray(k.depth), np.asarray(r.depth), atol=1e-4)
    assert (np.asarray(k.geom) != np.asarray(r.geom)).sum() <= 1
    np.testing.assert_allclose(np.asarray(k.rgb), np.asarray(r.rgb), atol=1e-3)


def test_vmap_equals_single_frames(primitives):
    m, d = primitives
    cfg = SN.CameraConfig(width=16, height=12, vfov_deg=90.0, max_depth=12.0)
    cam = SN.Camera(m, cfg)
    poses = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 2.0, 1.0], [-3.0, 1.0, -2.0], [2.0, -2.0, 3.0]], jnp.float32)
    xp = jnp.broadcast_to(jnp.asarray(d.geom_xpos, jnp.float32), (4, m.ngeom, 3))
    xm = jnp.broadcast_to(jnp.asarray(d.geom_xmat, jnp.float32), (4, m.ngeom, 9))
    batch = jax.jit(jax.vmap(cam.render_geoms))(xp, xm, poses)
    single = jax.jit(cam.render_geoms)
    for i in range(4):
        one = single(xp[i], xm[i], poses[i])
        for a, b in zip(one, batch):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b)[i], atol=1e-5)


# ------------------------------------------------------------------ house + simulator integration


def _room_centre_poses(scene) -> np.ndarray:
    """f32[4 * rooms, 3]: every room's floor centre, four headings each."""
    poses = []
    for r in range(scene.num_rooms):
        f = scene.room_floors[r][scene.room_floor_valid[r]][0]
        for yaw in (0.3, 1.9, -1.2, 3.0):
            poses.append([(f[0] + f[2]) / 2, (f[1] + f[3]) / 2, yaw])
    return np.asarray(poses, np.float32)


@pytest.mark.skipif(not os.path.exists(HOUSE), reason="scenes/house.xml not present")
def test_house_views_exact_with_default_k():
    """Default CameraConfig on the house: free-space poses are certified and equal mj_ray."""
    from hron_jax.scenes import load_scene

    scene = load_scene(HOUSE)
    m, d = _model_data(path=HOUSE)
    cfg = SN.CameraConfig()
    cam = SN.Camera(m, cfg, scene.geom_instance, scene.geom_class)
    fn = jax.jit(jax.vmap(cam.render_geoms, in_axes=(None, None, 0)))
    poses = _room_centre_poses(scene)
    out = fn(jnp.asarray(d.geom_xpos, jnp.float32), jnp.asarray(d.geom_xmat, jnp.float32), jnp.asarray(poses))
    assert np.all(np.asarray(out.uncertain) == 0)
    for i in range(0, len(poses), 3):
        one = jax.tree_util.tree_map(lambda x: x[i], out)
        RayRef(m, d, cfg, poses[i]).check(one)
        hit = np.asarray(one.geom) >= 0
        g = np.asarray(one.geom)[hit]
        np.testing.assert_array_equal(np.asarray(one.instance)[hit], scene.geom_instance[g])
        np.testing.assert_array_equal(np.asarray(one.semantic)[hit], scene.geom_class[g])


def test_simulator_integration_excludes_agent():
    """Camera.for_simulator on box_room: the camera sits inside the agent's capsule but never sees
    it; objects placed by mocap show with their node index; equals mj_ray with bodyexclude."""
    from hron_jax.scenes import load_scene
    from hron_jax.sim import Simulator

    scene = load_scene(BOX_ROOM)
    sim = Simulator.from_file(BOX_ROOM)
    cfg = SN.CameraConfig(width=32, height=32, vfov_deg=60.0)
    cam = SN.Camera.for_simulator(sim, cfg, scene=scene)
    apple = scene.index_of("object:apple:0")
    mpos = np.array(sim.default_mocap_pos, np.float32)
    mpos[scene.mocap_id[apple]] = [-2.0, 0.0, 0.795]  # on the table
    pose = jnp.asarray([-1.0, 0.0, math.pi], jnp.float32)  # 1 m from the apple, facing the table
    d = jax.jit(sim.init)(pose, jnp.asarray(mpos), jnp.asarray(np.tile([1.0, 0, 0, 0], (2, 1))))
    out = jax.jit(cam.render)(d, pose)
    geom = np.asarray(out.geom)
    assert not np.isin(geom, sim.agent_geoms).any()
    assert (np.asarray(out.instance) == apple).any()
    assert (np.asarray(out.instance) == scene.index_of("furniture:table:0")).any()
    m = sim.mj_model
    dn = mujoco.MjData(m)
    dn.qpos[sim.qpos_adr] = np.asarray(pose)
    dn.mocap_pos[:] = mpos
    mujoco.mj_kinematics(m, dn)
    RayRef(m, dn, cfg, np.asarray(pose), exclude_body=sim.agent_body).check(out)
    # without exclusion mj_ray would hit the capsule from inside: the exclusion matters
    assert np.isin(RayRef(m, dn, cfg, np.asarray(pose)).g, sim.agent_geoms).all()
