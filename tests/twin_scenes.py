"""Rendered twin scenes shared by the test files of one pytest process.

A rendered scene (camera image and a full-detector fluoroscopy DRR per view) costs seconds of CPU, and several files
ask for the same one. Scenes are frozen dataclasses; no test may write into their arrays.
"""

from functools import lru_cache

from drillnav.drivers.sim.scene import Scene, make_scene


@lru_cache(maxsize=4)
def rendered_scene(seed: int, views: str) -> Scene:
    """``make_scene(seed=seed, views=views)``, rendered once per process."""
    return make_scene(seed=seed, views=views)
