"""The profiling attribution of `python -m hron_jax.bench profile` / `compile --by-source`: XLA ops
of a trace are mapped to the hron_jax module whose code emitted them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hron_jax.bench.compile import deep_tracebacks, hlo_by_source, hlo_instructions, instruction_sources
from hron_jax.bench.profile import op_times
from hron_jax.ppo import compute_gae


@pytest.fixture
def deep_stacks():
    limit = jax.config.jax_traceback_in_locations_limit
    deep_tracebacks()
    yield
    jax.config.update('jax_traceback_in_locations_limit', limit)  # other tests compile leaner


def test_profiled_ops_are_attributed_to_their_source_module(tmp_path, deep_stacks):
    T, B = 64, 256
    rng = np.random.default_rng(0)
    reward, value = (jnp.asarray(rng.normal(size=(T, B)), jnp.float32) for _ in range(2))
    done = jnp.asarray(rng.random((T, B)) < 0.1)
    final_value, last_value = jnp.zeros((T, B)), jnp.ones(B)

    def gae_then_loss(reward, value):  # ppo.py's GAE, then a reduction of this file's own
        adv, target = compute_gae(reward, value, done, done & False, final_value, last_value, 0.99, 0.95)
        return jnp.square(adv - target).sum()

    fn = jax.jit(gae_then_loss).lower(reward, value).compile()
    sources = instruction_sources(fn.as_text())
    assert 'ppo.py' in {s for _, s, _ in sources.values()}
    assert any(
        'scan' in name_stack or 'while' in name_stack
        for _, s, name_stack in sources.values()
        if s == 'ppo.py'
    )
    assert sum(hlo_by_source(fn.as_text()).values()) == len(sources)
    # bench compile's count: the same instructions plus the parameters instruction_sources skips
    parameters = sum(' parameter(' in line for line in fn.as_text().splitlines())
    assert parameters >= 2 and hlo_instructions(fn.as_text()) == len(sources) + parameters
    jax.block_until_ready(fn(reward, value))
    with jax.profiler.trace(str(tmp_path)):
        jax.block_until_ready(fn(reward, value))
    (path,) = tmp_path.glob('**/*.xplane.pb')
    times = op_times(str(path))
    assert times and set(times) <= set(sources), set(times) - set(sources)
    assert all(t >= 0 for t in times.values())
    # GAE's reverse scan (a while loop) is ppo.py's; the only ops of no module are XLA's copies
    by_source = {sources[n][1] for n in times}
    assert 'ppo.py' in by_source
    assert all(
        s in ('ppo.py', "(XLA's own: no source)") or s.startswith('(no hron_jax frame)') for s in by_source
    )


def test_ops_without_our_frames_name_their_library(deep_stacks):
    # JAX drops its own frames from op stacks, so library code that is not JAX's (here optax, in
    # the chunk MJX) is what an op without a hron_jax frame can name
    import optax

    opt = optax.adam(1e-3)
    params = {'w': jnp.ones((4, 3))}
    fn = jax.jit(lambda g, s: opt.update(g, s, params)[0]).lower(params, opt.init(params)).compile()
    sources = {s for _, s, _ in instruction_sources(fn.as_text()).values()}
    assert '(no hron_jax frame) via optax' in sources, sources
