"""Fit marble's sigma_a and sigma_s (RGB, 1/mm) to a rendered target, starting 2x / 0.5x off.

.venv/bin/python examples/fit_rendered_target.py
"""

from pathlib import Path

import numpy as np

import sssjax

root = Path(__file__).resolve().parent.parent
scene = sssjax.load_scene(root / "scenes" / "marble_cube.toml").with_settings(
    width=96, height=96, spp=4, sss_cloud_size=4096
)
target = sssjax.render(scene, 0)
true = scene.media()["marble"]
init = {"sigma_a": np.asarray(true.sigma_a) * 2.0, "sigma_s": np.asarray(true.sigma_s) * 0.5}
result = sssjax.fit(scene, target, init=init, seed=0, progress=True)
print(result.summary())
print("true sigma_a", np.asarray(true.sigma_a), "sigma_s", np.asarray(true.sigma_s))
