"""Writes the images of tests/data/bad_images (run from the repository root):

.venv/bin/python tests/data/bad_images/make.py
"""

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from sssjax.imageio import write_image

HERE = Path(__file__).parent
write_image(HERE / "target.exr", np.full((8, 8, 3), 0.1))  # right size for tiny_scene.toml
write_image(HERE / "wrong_size.exr", np.full((9, 8, 3), 0.1))  # 8 wide, 9 high
write_image(HERE / "black.exr", np.zeros((8, 8, 3)))
nan = np.full((8, 8, 3), 0.1, np.float32)
nan[2, 3] = np.nan  # write_image refuses NaN: through OpenImageIO directly
out = oiio.ImageOutput.create(str(HERE / "nan.exr"))
out.open(str(HERE / "nan.exr"), oiio.ImageSpec(8, 8, 3, "float"))
out.write_image(nan)
out.close()
(HERE / "corrupt.exr").write_bytes(b"v/1\x01" + bytes(range(256)) * 2)  # EXR magic, then junk
(HERE / "not_an_image.exr").write_text("this is a text file named .exr\n")
write_image(HERE / "no_metadata.exr", np.full((16, 16, 3), 0.1))  # no pixel size, no beam
