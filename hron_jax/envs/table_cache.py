"""Cache of a scene's episode tables (`placement.build_tables`), in the process and on disk.

Role: the navigation envs build their tables through `episode_tables`. Building them is mostly
geodesic solves (one field per candidate target point) and their XLA compiles: ~12-17 s for
house.xml on 2 CPU cores, the same in every train.py, eval.py, analysis or test process that
builds the scene's env. A cached copy loads in a fraction of a second and is bitwise the same.

    episode_tables(scene, model, config, **kwargs) -> EpisodeTables   build_tables' arguments
    table_key(scene, model, config, **kwargs) -> str                   sha256 hex of all inputs

Key: the scene's tables (every field, and its MuJoCo model), the compiled model the agent moves
in (its MJB bytes), the PlacementConfig and keyword arguments, the source of the hron_jax package,
the versions of jax, jaxlib, numpy and mujoco, and JAX's backend (CPU and GPU solves may round
differently). Any change to any of them builds afresh, so a cached table is never stale.

Where: $HRON_JAX_TABLES_CACHE, else ~/.cache/hron_jax/tables, one <key>.npz per table set
(house.xml's: 12 MB, fields in float16), the MAX_FILES most recently used kept;
HRON_JAX_TABLES_CACHE=none keeps only the in-process copy. Files are written to a temporary name
and renamed, so processes that build the same tables at once never read a partial file; an
unreadable file is rebuilt and replaced. The arrays are read-only, since every env of a process
that builds the same tables shares them.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
import tempfile
from pathlib import Path

import numpy as np

from hron_jax.envs import placement as P
from hron_jax.geodesic import OccupancyGrid
from hron_jax.paths import CACHE_ROOT

CACHE_ENV = 'HRON_JAX_TABLES_CACHE'
MAX_FILES = 32  # most recently used table files kept (a house's: ~12 MB)
_PACKAGE = Path(__file__).resolve().parents[1]
_memory: dict[str, P.EpisodeTables] = {}


def cache_dir() -> Path | None:
    """The on-disk cache directory, or None when $HRON_JAX_TABLES_CACHE is 'none'."""
    value = os.environ.get(CACHE_ENV)
    if value and value.lower() == 'none':
        return None
    return Path(value) if value else Path(CACHE_ROOT) / 'tables'


@functools.cache  # the code this process runs is the code it imported
def _source_digest() -> bytes:
    h = hashlib.sha256()
    for f in sorted(_PACKAGE.rglob('*.py')):
        h.update(str(f.relative_to(_PACKAGE)).encode())
        h.update(f.read_bytes())
    return h.digest()


def _model_bytes(model) -> bytes:
    import mujoco

    buf = np.empty(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buf)
    return buf.tobytes()


def _update(h, value) -> None:
    if isinstance(value, np.ndarray):
        h.update(f'{value.dtype.str}{value.shape}'.encode())
        h.update(np.ascontiguousarray(value).tobytes())
    else:
        h.update(repr(value).encode())


def table_key(scene, model, config: P.PlacementConfig | None = None, **kwargs) -> str:
    """sha256 hex of everything build_tables' result depends on (see the module docstring);
    config None is the default PlacementConfig."""
    import jax
    import jaxlib
    import mujoco

    h = hashlib.sha256()
    for f in dataclasses.fields(scene):
        if f.name == 'path':  # the same scene under another path gives the same tables
            continue
        value = getattr(scene, f.name)
        h.update(f.name.encode())
        if f.name == 'model':
            h.update(_model_bytes(value))
        else:
            _update(h, value)
    h.update(_model_bytes(model))
    _update(h, config or P.PlacementConfig())
    _update(h, sorted(kwargs.items()))
    h.update(_source_digest())
    _update(
        h, (jax.__version__, jaxlib.__version__, np.__version__, mujoco.__version__, jax.default_backend())
    )
    return h.hexdigest()


def _save(tables: P.EpisodeTables, path: Path) -> None:
    arrays = {}
    for f in dataclasses.fields(tables):
        value = getattr(tables, f.name)
        if f.name == 'grid':
            arrays['grid.free'] = np.asarray(value.free)
            arrays['grid.fine'] = np.zeros((0, 0), bool) if value.fine is None else np.asarray(value.fine)
            arrays['grid.scalars'] = np.array(
                [*value.origin, value.cell_size, value.agent_radius], np.float64
            )
        else:
            arrays[f.name] = np.asarray(value)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix='.tmp')
    try:
        with os.fdopen(fd, 'wb') as out:
            np.savez(out, **arrays)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _load(path: Path) -> P.EpisodeTables:
    with np.load(path, allow_pickle=False) as z:
        fine = z['grid.fine']
        x, y, cell, radius = z['grid.scalars'].tolist()
        grid = OccupancyGrid(z['grid.free'], (x, y), cell, radius, fine=fine if fine.size else None)
        values = {}
        for f in dataclasses.fields(P.EpisodeTables):
            if f.name != 'grid':
                values[f.name] = int(z[f.name]) if f.type in ('int', int) else z[f.name]
    return P.EpisodeTables(grid=grid, **values)


def episode_tables(scene, model, config: P.PlacementConfig | None = None, **kwargs) -> P.EpisodeTables:
    """build_tables(scene, model, config, **kwargs), from the cache when it holds them."""
    config = config or P.PlacementConfig()
    key = table_key(scene, model, config, **kwargs)
    if key in _memory:
        return _memory[key]
    where = cache_dir()
    path = None if where is None else where / f'{key}.npz'
    tables = None
    if path is not None and path.exists():
        try:
            tables = _load(path)
        except Exception:  # damaged (cut short, not a zip, a field missing): build it again
            tables = None
    if tables is None:
        tables = P.build_tables(scene, model, config, **kwargs)
        if path is not None:
            try:
                _save(tables, path)
                _prune(path.parent)
            except OSError:  # a read-only or full disk only costs the next process a build
                pass
    else:
        try:
            os.utime(path)  # recently used: the last to be pruned
        except OSError:
            pass
    _freeze(tables)
    _memory[key] = tables
    return tables


def _prune(where: Path) -> None:
    """Delete all but the MAX_FILES most recently used table files: every edit of hron_jax's
    source keys new files, and the old ones are never read again."""
    files = sorted(where.glob('*.npz'), key=lambda f: f.stat().st_mtime, reverse=True)
    for f in files[MAX_FILES:]:
        f.unlink(missing_ok=True)


def _freeze(tables: P.EpisodeTables) -> None:
    """Read-only arrays: every env of the process shares them, so a write would be a bug."""
    grid = tables.grid
    for value in [getattr(tables, f.name) for f in dataclasses.fields(tables)] + [grid.free, grid.fine]:
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
