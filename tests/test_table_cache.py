"""hron_jax.envs.table_cache: a cached scene's episode tables are bitwise the ones build_tables
makes, every input of build_tables is in the key, and a damaged or absent cache only costs a build."""

import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from hron_jax.envs import placement as P
from hron_jax.envs import table_cache as TC
from hron_jax.paths import REPO_ROOT
from hron_jax.scenes.loader import load_scene
from hron_jax.sim import SimConfig, Simulator

SCENE = Path(REPO_ROOT) / 'scenes' / 'symmetric_room.xml'


@pytest.fixture(scope='module')
def built():
    scene = load_scene(SCENE)
    model = Simulator.from_file(SCENE).mj_model
    return scene, model, P.build_tables(scene, model, success_distance=1.0)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv(TC.CACHE_ENV, str(tmp_path / 'tables'))
    monkeypatch.setattr(TC, '_memory', {})
    return tmp_path / 'tables'


def assert_same_tables(a: P.EpisodeTables, b: P.EpisodeTables):
    for f in dataclasses.fields(P.EpisodeTables):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == 'grid':
            assert (x.origin, x.cell_size, x.agent_radius) == (y.origin, y.cell_size, y.agent_radius)
            assert [type(v) for v in (*x.origin, x.cell_size, x.agent_radius)] == [
                type(v) for v in (*y.origin, y.cell_size, y.agent_radius)
            ]
            for u, v in ((x.free, y.free), (x.fine, y.fine)):
                assert (u is None) == (v is None)
                if u is not None:
                    np.testing.assert_array_equal(np.asarray(u), np.asarray(v), strict=True)
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, strict=True)  # dtype and shape too; inf == inf
        else:
            assert type(x) is type(y) and x == y, f.name


def test_tables_round_trip_bitwise_through_the_disk(built, cache, monkeypatch):
    scene, model, fresh = built
    build = P.build_tables
    calls = []
    monkeypatch.setattr(P, 'build_tables', lambda *a, **k: calls.append(1) or build(*a, **k))
    first = TC.episode_tables(scene, model, success_distance=1.0)
    assert calls == [1] and [p.name for p in cache.iterdir()] == [
        TC.table_key(scene, model, success_distance=1.0) + '.npz'
    ]
    assert_same_tables(first, fresh)
    assert TC.episode_tables(scene, model, success_distance=1.0) is first  # in-process copy
    monkeypatch.setattr(TC, '_memory', {})  # a new process: from the disk, no build
    (path,) = cache.iterdir()
    os.utime(path, (0, 0))
    loaded = TC.episode_tables(scene, model, success_distance=1.0)
    assert calls == [1] and path.stat().st_mtime > 0  # used now: the last to be pruned
    assert_same_tables(loaded, fresh)
    assert loaded.fields.dtype == np.float16 and np.isinf(loaded.fields).any()


def test_every_input_is_in_the_key(built, tmp_path):
    scene, model, _ = built
    key = TC.table_key(scene, model, P.PlacementConfig(), success_distance=1.0)
    assert key == TC.table_key(scene, model, P.PlacementConfig(), success_distance=1.0)
    # the same file elsewhere is the same scene
    copy = tmp_path / 'elsewhere.xml'
    shutil.copy(SCENE, copy)
    assert TC.table_key(load_scene(copy), model, P.PlacementConfig(), success_distance=1.0) == key
    others = [
        TC.table_key(scene, model, P.PlacementConfig(robust_margin=0.3), success_distance=1.0),
        TC.table_key(scene, model, P.PlacementConfig(), success_distance=1.2),
        TC.table_key(scene, model, P.PlacementConfig(), success_distance=1.0, agent_radius=0.25),
        # the agent's collider changes the model it moves in
        TC.table_key(
            scene,
            Simulator.from_file(SCENE, SimConfig(radius=0.25)).mj_model,
            P.PlacementConfig(),
            success_distance=1.0,
        ),
        # an annotation of the scene (a slot moved by 1 cm)
        TC.table_key(
            dataclasses.replace(scene, slot_center=scene.slot_center + np.array([0.01, 0.0, 0.0])),
            model,
            P.PlacementConfig(),
            success_distance=1.0,
        ),
    ]
    assert len({key, *others}) == 1 + len(others)


def test_a_damaged_file_is_rebuilt_and_none_writes_nothing(built, cache, monkeypatch):
    scene, model, fresh = built
    cache.mkdir(parents=True)
    path = cache / (TC.table_key(scene, model, success_distance=1.0) + '.npz')
    path.write_bytes(b'PK\x03\x04 not a zip')  # e.g. a copy cut short
    assert_same_tables(TC.episode_tables(scene, model, success_distance=1.0), fresh)
    monkeypatch.setattr(TC, '_memory', {})
    assert_same_tables(TC._load(path), fresh)  # replaced by a good file
    monkeypatch.setattr(TC, '_memory', {})
    monkeypatch.setenv(TC.CACHE_ENV, 'none')
    path.unlink()
    assert_same_tables(TC.episode_tables(scene, model, success_distance=1.0), fresh)
    assert list(cache.iterdir()) == []


def test_only_the_most_recently_used_files_are_kept(tmp_path, monkeypatch):
    monkeypatch.setattr(TC, 'MAX_FILES', 2)
    for age, name in enumerate(['newest', 'newer', 'old', 'oldest']):
        (tmp_path / f'{name}.npz').write_bytes(b'')
        os.utime(tmp_path / f'{name}.npz', (1e9 - age, 1e9 - age))
    (tmp_path / 'notes.txt').write_text('not a table')
    TC._prune(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['newer.npz', 'newest.npz', 'notes.txt']
