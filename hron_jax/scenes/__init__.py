"""Household scenes: fixed vocabularies, the annotated-MJCF loader, MJCF writers, generator, plots.

`load_scene(path) -> Scene` is the entry point; see docs/scene_format.md for the file format and
hron_jax/scenes/loader.py for the tables (names, shapes) a Scene carries.
"""

from . import vocabulary
from .loader import Scene, SceneError, goal_table, load_scene, object_fits, room_at, scene_from_model

__all__ = [
    "Scene",
    "SceneError",
    "load_scene",
    "scene_from_model",
    "room_at",
    "goal_table",
    "object_fits",
    "vocabulary",
]
