"""Train a HRON policy with PPO: `python train.py --task exploratory --num-envs 64` (see --help).

Thin entry point; the logic (config, jitted program, checkpoints, logs) is hron_jax/training.py.
"""
import sys

from hron_jax.training import main

if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
