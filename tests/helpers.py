"""Shared test helpers: the finite-difference check and small scenes.

Scenes are kept tiny (a few dozen pixels, few spp, small clouds): compiling dominates the
suite's time, and scenes of the same structure share compiled code within a test module.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import sssjax

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"


def central_differences(f, x, h: float = 1e-6, *, relative: bool = True, floor: float = 0.0):
    """Central differences of `f` at `x` (float64): column `i` is
    `(f(x + e_i) - f(x - e_i)) / (2 |e_i|)` with step `h * max(|x_i|, floor)` (`relative`) or
    `h`. **Returns:** an array of shape `f(x).shape + (x.size,)`."""
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        step = h * max(abs(float(x.flat[i])), floor) if relative else h
        e = np.zeros_like(x)
        e.flat[i] = step
        cols.append(
            (np.asarray(f(x + e), np.float64) - np.asarray(f(x - e), np.float64)) / (2 * step)
        )
    return np.stack(cols, axis=-1)


def shipped_scene(name: str, **settings) -> sssjax.Scene:
    """A scene of `scenes/` (`name` without `.toml`), with settings changed (`width=`, ...)."""
    scene = sssjax.load_scene(SCENES / f"{name}.toml")
    return scene.with_settings(**settings) if settings else scene


def small_cube(preset: str = "marble", **settings) -> sssjax.Scene:
    """`marble_cube.toml` at 40 x 40 pixels, 4 spp, a 2048-point cloud, 2 x 2 light samples,
    the cube's medium replaced by the preset `preset`; `settings` change more."""
    scene = shipped_scene(
        "marble_cube", width=40, height=40, spp=4, sss_cloud_size=2048, light_samples=2
    )
    mats = dict(scene.materials)
    m = mats["marble"]
    mats["marble"] = type(m)(m.name, m.type, medium=sssjax.preset(preset))
    scene = scene.replace(materials=mats)
    return scene.with_settings(**settings) if settings else scene


def slab_scene(
    material: dict,
    *,
    width=8,
    spp=4,
    cloud=16384,
    single=False,
    size=60.0,
    thick=20.0,
    light_height=1000.0,
    intensity=1e6,
    seed=0,
) -> sssjax.Scene:
    """A flat slab of `material` (`size` x `thick` x `size` mm) lit from straight above by a
    distant point light, seen from above through a 1 degree field of view."""
    return sssjax.load_scene(
        {
            "camera": {
                "origin": [0.0, 150.0, 60.0],
                "target": [0.0, 0.0, 0.0],
                "fov": 1.0,
                "width": width,
                "height": width,
            },
            "render": {"spp": spp, "light_samples": 1, "max_depth": 1, "seed": seed},
            "sss": {"cloud_size": cloud, "single_scattering": single},
            "lights": [
                {
                    "type": "point",
                    "position": [0.0, light_height, 0.0],
                    "intensity": [intensity] * 3,
                }
            ],
            "materials": {"m": material},
            "shapes": [
                {
                    "type": "cube",
                    "material": "m",
                    "size": [size, thick, size],
                    "translate": [0.0, -thick / 2, 0.0],
                }
            ],
        }
    )
