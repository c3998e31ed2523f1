"""Gradient of an image loss with respect to sigma_a and sigma_s (per RGB channel, per mm).

Trace once, then differentiate the cheap shading pass.

    .venv/bin/python examples/gradient.py
"""

from pathlib import Path

import jax
import jax.numpy as jnp

import sssjax
from sssjax import Medium

root = Path(__file__).resolve().parent.parent
scene = sssjax.load_scene(root / "scenes" / "marble_cube.toml").with_settings(
    width=64, height=64, spp=4
)
target = sssjax.render(scene, 0)  # marble
transport = sssjax.trace(scene, 0)
base = scene.media()["marble"]


def loss(sigma_a, sigma_s):
    img = sssjax.shade_image(transport, {"marble": Medium(sigma_a, sigma_s, base.g, base.eta)})
    return jnp.mean((img - target) ** 2)


sa, ss = base.sigma_a * 2.0, base.sigma_s * 0.5  # a wrong guess
g_a, g_s = jax.grad(loss, argnums=(0, 1))(sa, ss)
print("loss at the wrong guess:", float(loss(sa, ss)))
print("d loss / d sigma_a [per 1/mm]:", g_a)
print("d loss / d sigma_s [per 1/mm]:", g_s)
