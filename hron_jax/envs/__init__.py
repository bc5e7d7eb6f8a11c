"""The three HRON tasks behind one factory.

    config = env_config('choice' | 'directed' | 'exploratory', **options)   # typed, hashable
    env = make_env(task, scene=None, config=None, **options)

choice: hron_jax.envs.choice.ChoiceEnv; options are ChoiceConfig fields; no scene.
directed / exploratory: hron_jax.envs.navigation.NavigationEnv; scene is a path or a loaded Scene
(default scenes/symmetric_room.xml and scenes/house.xml of this repository); options are NavConfig
fields, plus `image_size=S` as a shortcut for a square S x S camera (other camera settings:
`camera=CameraConfig(...)`). TASKS / NAV_TASKS are the one home of the task names.
"""

from __future__ import annotations

import dataclasses

from hron_jax.envs.base import AutoResetWrapper, Env, EnvState
from hron_jax.envs.choice import ChoiceConfig, ChoiceEnv
from hron_jax.paths import DEFAULT_SCENES

NAV_TASKS = ('directed', 'exploratory')
TASKS = ('choice',) + NAV_TASKS


def env_config(task: str, **options):
    """The task's config (ChoiceConfig, or NavConfig with its task set) with `options` applied
    (field names; `image_size=S` sets a square S x S camera)."""
    if task not in TASKS:
        raise ValueError(f'unknown task {task!r}; valid tasks: {", ".join(TASKS)}')
    if 'task' in options:
        raise TypeError("pass the task as the first argument, not as an option")
    if task == 'choice':
        return _replace(ChoiceConfig(), options, 'the choice task')
    from hron_jax.envs.navigation import NavConfig  # deferred: MuJoCo / MJX

    options = dict(options)
    size = options.pop('image_size', None)
    config = _replace(NavConfig(task=task), options, f'the {task} task')
    if size is not None:
        config = dataclasses.replace(
            config, camera=dataclasses.replace(config.camera, width=int(size), height=int(size))
        )
    return config


def _replace(config, options: dict, what: str):
    names = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(options) - names)
    if unknown:
        raise TypeError(f'unknown option(s) {unknown} for {what}; valid: {sorted(names)}')
    return dataclasses.replace(config, **options)


def make_env(task: str, scene=None, config=None, **options):
    """Build a task env (see the module docstring); `config` (the task's config, default
    env_config(task)) with `options` applied."""
    config = env_config(task, **options) if config is None else _replace(config, options, task)
    if task == 'choice':
        if scene is not None:
            raise ValueError('the choice task has no scene')
        return ChoiceEnv(config)
    from hron_jax.envs.navigation import NavigationEnv

    if config.task != task:
        raise ValueError(f'config is for the {config.task} task, not {task}')
    return NavigationEnv(DEFAULT_SCENES[task] if scene is None else scene, config)


__all__ = [
    'make_env',
    'env_config',
    'TASKS',
    'NAV_TASKS',
    'DEFAULT_SCENES',
    'Env',
    'EnvState',
    'AutoResetWrapper',
    'ChoiceEnv',
    'ChoiceConfig',
]
