"""Where the repository's files are: its root, the scenes (and each task's default), repo-relative
paths; and the root of the caches hron_jax keeps per user (CACHE_ROOT: XLA's compilations, the
scenes' episode tables). Imports no JAX.

Scenes named in a run's config.json are stored relative to the repository root when they lie
inside it (`portable_path`), so run directories survive moving the checkout; `resolve` turns
such a path back into an absolute one.
"""

from __future__ import annotations

import os

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE_DIR = os.path.join(REPO_ROOT, 'scenes')
CACHE_ROOT = os.path.join(os.path.expanduser('~'), '.cache', 'hron_jax')
# The scene each navigation task trains in by default.
DEFAULT_SCENES = {
    'directed': os.path.join(SCENE_DIR, 'symmetric_room.xml'),
    'exploratory': os.path.join(SCENE_DIR, 'house.xml'),
}


def portable_path(path: str) -> str:
    """`path` relative to the repository root when it lies inside it, else absolute."""
    path = os.path.abspath(os.path.join(REPO_ROOT, path))
    rel = os.path.relpath(path, REPO_ROOT)
    return path if rel.startswith(os.pardir) else rel


def resolve(path: str) -> str:
    """Absolute path of `path` (a relative one is relative to the repository root)."""
    return os.path.join(REPO_ROOT, path)
