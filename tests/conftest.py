"""Test-session settings: the scenes' episode tables (hron_jax.envs.table_cache) are cached in a
directory of this session, shared with the train.py / eval.py processes the tests start, rather
than in ~/.cache."""

import os
import shutil
import tempfile

_CACHE = tempfile.mkdtemp(prefix='hron_jax_tables_')


def pytest_configure(config):
    os.environ.setdefault('HRON_JAX_TABLES_CACHE', _CACHE)


def pytest_unconfigure(config):
    shutil.rmtree(_CACHE, ignore_errors=True)
