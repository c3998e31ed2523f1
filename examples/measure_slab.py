"""Jensen's measurement step, end to end: render the beam-lit marble slab, then recover
sigma_a and sigmap_s (RGB, 1/mm) from the image's radial profile.

.venv/bin/python examples/measure_slab.py

The same from the command line:

    sssjax render scenes/measurement_slab.toml -o out/slab.exr
    sssjax measure out/slab.exr          # pixel size, beam power, eta from the EXR metadata
"""

from pathlib import Path

import numpy as np

import sssjax
from sssjax.measure import find_center, fit_profile, image_to_reflectance, radial_profile
from sssjax.plots import measurement_plot

root = Path(__file__).resolve().parent.parent
scene = sssjax.load_scene(root / "scenes" / "measurement_slab.toml")
image = np.asarray(sssjax.render(scene, 0, progress=True))
true = scene.media()["sample"]
eta = float(true.eta)

# radiance -> R_d units (per watt entering), using the beam's known power of 1 W
R = image_to_reflectance(image, eta, power=1.0)
center = find_center(image)
profile = radial_profile(R, center, scene.camera.pixel_size_mm)
# the diffusion transport renders the beam's multiple scattering only: orders="multiple";
# the centre (within 1 mm) is left out
fit = fit_profile(profile, eta, r_min=1.0, orders="multiple")

for c, ch in enumerate("RGB"):
    print(
        f"{ch}: sigma_a {fit.sigma_a[c]:.5f} +- {fit.sigma_a_stderr[c]:.1g} "
        f"(true {float(true.sigma_a[c]):.5f}), sigmap_s {fit.sigmap_s[c]:.4f} "
        f"+- {fit.sigmap_s_stderr[c]:.1g} (true {float(true.sigmap_s[c]):.4f}) 1/mm"
    )
out = measurement_plot(profile, fit, eta, root / "out" / "measure_slab_profile.png", r_min=1.0)
print(f"wrote {out}")
