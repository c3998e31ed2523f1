"""Forward render from Python: load a scene, change its material, render, write EXR + PNG.

.venv/bin/python examples/render_from_python.py
"""

from pathlib import Path

import sssjax

root = Path(__file__).resolve().parent.parent
scene = sssjax.load_scene(root / "scenes" / "marble_cube.toml").with_settings(
    width=128, height=128, spp=16
)
image = sssjax.render(scene, seed=0, media={"marble": sssjax.preset("skin1")}, progress=True)
out = root / "out" / "examples"
for name in ("skin_cube.exr", "skin_cube.png"):
    path = sssjax.imageio.write_image(out / name, image)
    print(f"wrote {path}")
