"""Benchmarks: `python -m hron_jax.bench env|graph|model|train|conv|geodesic|discovery [options]`.

One module per benchmark, each saying in its docstring what it measures and what it prints
(`python -m hron_jax.bench SUBCOMMAND --help` shows it):
    env       simulator + camera env steps/s vs native MuJoCo        (bench/env.py)
    graph     scene-graph / metric-map update cost per env step       (bench/graph.py)
    model     actor-critic forward / forward+grad ms per variant      (bench/model.py)
    train     PPO train env steps/s (env + update) per num_envs       (bench/train.py)
    profile   device time of one PPO update per source module         (bench/profile.py)
    conv      conv encoder fwd+grad in lax.scan: nn.Conv vs PatchConv (bench/conv.py)
    geodesic  geodesic distance fields: rasterise + solve time        (bench/geodesic.py)
    discovery object first-discovery distance per category and camera size (bench/discovery.py)
Every subcommand prints the machine first and the load average last; table rows appear as soon
as they are measured. Shared helpers: bench/common.py. This package imports no JAX until a
benchmark runs: hron_jax.reproduction (tools/reproduce.py) imports `machine` from here.
"""

from .common import machine, machine_info  # noqa: F401
