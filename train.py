"""Train a HRON policy with PPO: `python train.py --task exploratory --num-envs 64` (see --help).

Thin entry point: the CLI is hron_jax/cli.py, training hron_jax/training.py, the run config
hron_jax/run_config.py.
"""

import sys

from hron_jax.cli import main

if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
