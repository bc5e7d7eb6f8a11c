"""MJX's Warp implementation as the Simulator's physics (`SimConfig.physics = 'warp'`).

Role
----
`WarpPhysics(mj_model, contacts_per_env).substeps(qpos, qvel, time, ctrl)` runs one env step's
substeps with `mjx.step` on MJX-Warp (kernels through a JAX FFI call; CUDA on NVIDIA GPUs, Warp's
CPU backend elsewhere) for a batch of N worlds of the Simulator's physics model and returns the
fields the rest of the code reads. Shapes: qpos f32[N, nq], qvel f32[N, nv], time f32[N], ctrl
f32[N, S, nu] (one row per substep) -> dict of f32[N, ...]: qpos, qvel, time.

Why a batch function and not a per-env `mjx.Data` carried through the env: MJX-Warp keeps one
contact pool of `naconmax` entries shared by all worlds of a call (contacts are not batched), so
its Data cannot be merged per env (the env's auto-reset `where`) and its pool size depends on how
many worlds a call steps. Here each call builds its Data from a template with a pool of
N x contacts_per_env entries (the pool is shared, so only the average must fit; constraint rows
are per world: 4 x contacts_per_env each) and only the
batched state leaves it. Under `jax.vmap` (nested or not) the batch is flattened into one call of
all worlds (a custom vmap rule), so a vmapped per-env use (N = 1 inside) steps every env in one
kernel launch per stage. Contacts, constraint rows and warm starts do not survive the call: the
agent is at rest after every env step (the Simulator's brake), so no state but the pose carries.

The template's uniform leaves (zeros, -1) are rebuilt as broadcasts in the trace instead of being
embedded as constants (the contact pool at 8192 envs would be ~10 MB of literals in the program).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

OUT_FIELDS = ("qpos", "qvel", "time")


def _traced_constant(x):
    """A template leaf as it should enter the trace: a broadcast when all its entries are equal."""
    x = np.asarray(x)
    if x.size and np.all(x == x.flat[0]):
        return jnp.full(x.shape, x.flat[0], x.dtype)
    return jnp.asarray(x)


class WarpPhysics:
    """Batched MJX-Warp substeps of one compiled MuJoCo model (see the module docstring)."""

    def __init__(self, mj_model: mujoco.MjModel, contacts_per_env: int):
        import warp

        if contacts_per_env < 1:
            raise ValueError("warp_contacts_per_env must be >= 1")
        warp.config.quiet = True  # no per-module load lines on stdout
        if hasattr(warp, "LOG_WARNING"):  # warp >= 1.18 logs those at INFO
            warp.config.log_level = warp.LOG_WARNING
        model = mjx.put_model(mj_model, impl="warp")
        # Warp's kernels printf a warning each time a line search stops at ls_iterations; the JAX
        # implementation stops there silently, and both then agree with native MuJoCo (tested).
        opt = model.opt.replace(_impl=model.opt._impl.replace(warn_overflow=0))
        self.model = model.replace(opt=opt)
        self.mj_model = mj_model
        self.contacts_per_env = contacts_per_env
        self._templates: dict[int, mjx.Data] = {}
        self.substeps = jax.custom_batching.custom_vmap(self._substeps)
        self.substeps.def_vmap(self._substeps_vmap)

    def _template(self, n: int) -> mjx.Data:
        """Host copy of one world's Data with a contact pool for n worlds (built once per n)."""
        if n not in self._templates:
            k = self.contacts_per_env
            # The pool is shared, but constraint rows are per world (one per frictionless contact):
            # 4 k = 32 rows, where native MuJoCo found at most 12 shallow contacts at once over
            # 40,000 random agent poses in the four houses (corners of several legs and panels).
            with jax.ensure_compile_time_eval():  # first built inside a trace
                d = mjx.make_data(self.mj_model, impl="warp", naconmax=n * k, njmax=4 * k)
                self._templates[n] = jax.tree.map(np.asarray, d)
        return self._templates[n]

    def _substeps(self, qpos, qvel, time, ctrl):
        template = jax.tree.map(_traced_constant, self._template(qpos.shape[0]))

        def world(q, v, t, c):
            d = template.replace(qpos=q, qvel=v, time=t)
            d, _ = jax.lax.scan(lambda d, u: (mjx.step(self.model, d.replace(ctrl=u)), None), d, c)
            return {f: getattr(d, f) for f in OUT_FIELDS}

        return jax.vmap(world)(qpos, qvel, time, ctrl)

    def _substeps_vmap(self, axis_size, in_batched, *args):
        # Fold the vmapped axis into the batch: one call steps all worlds (nested vmaps fold in turn).
        args = [a if b else jnp.broadcast_to(a, (axis_size,) + a.shape) for a, b in zip(args, in_batched)]
        out = self.substeps(*(a.reshape((-1,) + a.shape[2:]) for a in args))
        out = {f: x.reshape((axis_size, -1) + x.shape[1:]) for f, x in out.items()}
        return out, {f: True for f in out}
