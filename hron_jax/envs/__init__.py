"""The three HRON tasks behind one factory.

    env = make_env('choice' | 'directed' | 'exploratory', scene=None, **options)

choice: hron_jax.envs.choice.ChoiceEnv; options are ChoiceConfig fields; no scene.
directed / exploratory: hron_jax.envs.navigation.NavigationEnv; scene is a path or a loaded Scene
(default scenes/symmetric_room.xml and scenes/house.xml of this repository); options are NavConfig
fields, plus `image_size=S` as a shortcut for a square S x S camera (other camera settings:
`camera=CameraConfig(...)`).
"""
from __future__ import annotations

import dataclasses
import os

from hron_jax.envs.base import AutoResetWrapper, Env, EnvState
from hron_jax.envs.choice import ChoiceConfig, ChoiceEnv

TASKS = ('choice', 'directed', 'exploratory')
_SCENE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                          'scenes')
DEFAULT_SCENES = {
    'directed': os.path.join(_SCENE_DIR, 'symmetric_room.xml'),
    'exploratory': os.path.join(_SCENE_DIR, 'house.xml'),
}


def _config(cls, options: dict, what: str):
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(options) - names)
    if unknown:
        raise TypeError(f'unknown option(s) {unknown} for {what}; valid: {sorted(names)}')
    return cls(**options)


def make_env(task: str, scene=None, **options):
    """Build a task env (see the module docstring)."""
    if task not in TASKS:
        raise ValueError(f'unknown task {task!r}; valid tasks: {", ".join(TASKS)}')
    if task == 'choice':
        if scene is not None:
            raise ValueError('the choice task has no scene')
        return ChoiceEnv(_config(ChoiceConfig, options, 'the choice task'))
    # Deferred: the navigation envs pull in MuJoCo / MJX.
    from hron_jax.envs.navigation import NavConfig, NavigationEnv
    from hron_jax.sensors import CameraConfig

    options = dict(options)
    size = options.pop('image_size', None)
    if size is not None:
        cam = options.get('camera', CameraConfig())
        options['camera'] = dataclasses.replace(cam, width=int(size), height=int(size))
    if 'task' in options:
        raise TypeError("pass the task as make_env's first argument, not as an option")
    config = _config(NavConfig, dict(options, task=task), f'the {task} task')
    return NavigationEnv(DEFAULT_SCENES[task] if scene is None else scene, config)


__all__ = ['make_env', 'TASKS', 'DEFAULT_SCENES', 'Env', 'EnvState', 'AutoResetWrapper',
           'ChoiceEnv', 'ChoiceConfig']
