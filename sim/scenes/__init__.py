"""Test scenes for the twin: the built-in catalog, generated scrap and user YAML scene files.

`load_scene("t_piece")`, `load_scene("scrap:0:17")` (generator seed 0, piece 17; sim/scenes/scrap.py)
or `load_scene("configs/scenes/example_plate.yaml")` -> `Scene` in the robot base frame. Built-in scenes are built once per process; each call returns a fresh copy.
"""

from __future__ import annotations

import os
import zlib

from sim.appearance import parse_look, split_look

from sim.scenes.catalog import SCENE_NAMES, build_catalog_scene
from sim.scenes.model import Scene
from sim.scenes.scene_file import SceneError, load_scene_file

__all__ = ["SCENE_NAMES", "Scene", "SceneError", "load_scene"]


def load_scene(name_or_path: str | os.PathLike) -> Scene:
    """A catalog scene by name, or a user scene from a .yaml/.yml file path; any of them with a look
    (``@<finish>,<paint>,<light>[,<seed>]`` or ``@drawn``, sim.appearance) in the twin's camera."""
    ref, look = split_look(os.fspath(name_or_path))
    scene = _load(ref)
    if look is not None:
        from sim.scenes.scrap import parse_ref

        key = parse_ref(ref) or [zlib.crc32(ref.encode())]
        try:
            scene.appearance = parse_look(look, key)
        except ValueError as e:
            raise SceneError(f"{ref}@{look}: {e}") from None
    return scene


def _load(ref: str) -> Scene:
    if ref in SCENE_NAMES:
        return build_catalog_scene(ref)
    if ref.startswith("scrap:"):
        from sim.scenes.scrap import load_scrap, parse_ref

        if parse_ref(ref) is None:
            raise SceneError(f"bad generated piece {ref!r}: write scrap:<gen_seed>:<index>, e.g. scrap:0:17")
        return load_scrap(ref)
    if ref.lower().endswith((".yaml", ".yml")) or os.sep in ref or os.path.isfile(ref):
        return load_scene_file(ref)
    raise SceneError(f"unknown scene {ref!r}: use one of {', '.join(SCENE_NAMES)}, a generated piece "
                     "scrap:<gen_seed>:<index>, or a path to a .yaml scene file")
