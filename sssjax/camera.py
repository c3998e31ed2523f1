"""Pinhole and orthographic cameras: primary rays through jittered positions within pixels."""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .scene import Camera


def camera_rays(
    cam: Camera, pixel: Int[Array, " P"], jitter: Float[Array, "P S 2"]
) -> tuple[Float[Array, "P S 3"], Float[Array, "P S 3"]]:
    """Rays from the camera through `pixel` (flat index `y * width + x`) offset by `jitter`.

    **Arguments:** `jitter` in [0, 1)^2 is the position within the pixel (x right, y down).

    **Returns:** `(origin, direction)`, direction of unit length, world space (mm).
    """
    fwd, right, up = (jnp.asarray(v, dtype=float) for v in cam.basis())
    x = (pixel % cam.width).astype(jitter.dtype)[:, None] + jitter[..., 0]
    y = (pixel // cam.width).astype(jitter.dtype)[:, None] + jitter[..., 1]
    aspect = cam.width / cam.height
    if cam.projection == "orthographic":
        # parallel rays from the image plane through `origin`, `view_width` mm wide
        half_w = 0.5 * cam.view_width
        sx = (2.0 * x / cam.width - 1.0) * half_w
        sy = (1.0 - 2.0 * y / cam.height) * half_w / aspect
        o = jnp.asarray(cam.origin, dtype=float) + sx[..., None] * right + sy[..., None] * up
        return o, jnp.broadcast_to(fwd, o.shape)
    tan_half = math.tan(math.radians(cam.fov) / 2)
    sx = (2.0 * x / cam.width - 1.0) * tan_half * aspect
    sy = (1.0 - 2.0 * y / cam.height) * tan_half
    d = fwd + sx[..., None] * right + sy[..., None] * up
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    o = jnp.broadcast_to(jnp.asarray(cam.origin, dtype=float), d.shape)
    return o, d


def project(cam: Camera, points: Float[Array, "N 3"]) -> Float[Array, "N 2"]:
    """Continuous pixel coordinates (x right, y down) of world points; inverse of `camera_rays`."""
    fwd, right, up = (jnp.asarray(v, dtype=float) for v in cam.basis())
    v = jnp.asarray(points) - jnp.asarray(cam.origin, dtype=float)
    aspect = cam.width / cam.height
    if cam.projection == "orthographic":
        half_w = 0.5 * cam.view_width
        sx = (v @ right) / half_w
        sy = (v @ up) / (half_w / aspect)
    else:
        z = v @ fwd
        tan_half = math.tan(math.radians(cam.fov) / 2)
        sx = (v @ right) / z / (tan_half * aspect)
        sy = (v @ up) / z / tan_half
    return jnp.stack([(sx + 1) * cam.width / 2, (1 - sy) * cam.height / 2], axis=-1)
