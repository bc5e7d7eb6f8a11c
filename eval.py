"""Evaluate a train.py run or a reference policy: `python eval.py RUN_DIR` (see --help).

Thin entry point; the logic is hron_jax/evaluation.py.
"""

import sys

from hron_jax.evaluation import main

if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
