"""The constant environment light (`[[lights]] type = "environment"`) in the diffusion
transport, against closed forms (the volumetric transport's white furnace under it is in
`test_volumetric.py`)."""

from __future__ import annotations

import numpy as np

import sssjax

L_ENV = np.array([0.5, 1.0, 2.0])


def _scene(camera, materials, shapes, **render):
    r = {"spp": 16, "light_samples": 4, "max_depth": 1, "background": 0.0, **render}
    return sssjax.load_scene(
        {
            "camera": camera,
            "render": r,
            "sss": {"enabled": False},
            "lights": [{"type": "environment", "radiance": L_ENV.tolist()}],
            "materials": materials,
            "shapes": shapes,
        }
    )


def _ortho(origin, target, view_width, n=8):
    return {
        "origin": origin,
        "target": target,
        "projection": "orthographic",
        "view_width": view_width,
        "width": n,
        "height": n,
    }


def test_convex_diffuse_and_mirror_objects_see_the_whole_environment():
    """Alone, a convex diffuse object's every shadow ray escapes: `L = albedo L_env`
    exactly; a mirror reflects the environment: `L = reflectance L_env`; the background
    pixels around them see the environment itself."""
    R, n, vw = 5.0, 12, 14.0
    cam = _ortho([0, 0, 40], [0, 0, 0], vw, n)
    # pixels wholly inside / outside the sphere's disc, by their corners' distances
    edges = (np.arange(n + 1) / n - 0.5) * vw
    cx, cy = np.meshgrid(edges, edges)
    rc = np.hypot(cx, cy)
    corners = np.stack([rc[:-1, :-1], rc[1:, :-1], rc[:-1, 1:], rc[1:, 1:]])
    inside, outside = corners.max(0) < R, corners.min(0) > R
    for mat, want in (
        ({"type": "diffuse", "albedo": [0.6, 0.3, 0.9]}, np.array([0.6, 0.3, 0.9]) * L_ENV),
        ({"type": "mirror", "reflectance": 0.8}, 0.8 * L_ENV),
    ):
        sc = _scene(cam, {"m": mat}, [{"type": "sphere", "material": "m", "radius": R}])
        img = sssjax.render(sc)
        np.testing.assert_allclose(img[inside], np.broadcast_to(want, img[inside].shape), rtol=1e-4)
        np.testing.assert_allclose(img[outside], np.broadcast_to(L_ENV, img[outside].shape))
    assert inside.sum() >= 30 and outside.sum() >= 30


def test_a_floating_sphere_shades_the_floor_by_its_projected_solid_angle():
    """A floor point under a sphere (radius R, centre at distance D, at angle theta from the
    floor's normal) sees the environment except the sphere's cap, whose projected solid angle
    is `pi (R / D)^2 cos(theta)`: `E = pi L_env (1 - (R/D)^2 cos theta)`, `L = albedo E / pi`;
    the render against that closed form, averaged over each pixel's footprint."""
    R, h, albedo, n = 4.0, 10.0, 0.5, 8
    vw = 4.0
    cam = _ortho([0, 30, 30], [0, 0, 0], vw, n)
    floor = {
        "type": "quadmesh",
        "material": "floor",
        "vertices": [[-500, 0, -500], [-500, 0, 500], [500, 0, 500], [500, 0, -500]],
        "faces": [[0, 1, 2, 3]],
    }
    sc = _scene(
        cam,
        {"floor": {"type": "diffuse", "albedo": albedo}, "ball": {"type": "diffuse", "albedo": 0}},
        [floor, {"type": "sphere", "material": "ball", "radius": R, "translate": [0, h, 0]}],
        spp=64,
        light_samples=16,
        max_depth=0,
    )
    img = sssjax.render(sc)[..., 1] / L_ENV[1]  # grey: one channel
    # the floor point of each sub-pixel: orthographic rays along -(0, 1, 1)/sqrt 2
    s = 16
    c = ((np.arange(n * s) + 0.5) / s / n - 0.5) * vw
    u, v = np.meshgrid(c, -c)  # image x right, y up
    right = np.array([1.0, 0, 0])
    up = np.array([0.0, 1, -1]) / np.sqrt(2)
    o = u[..., None] * right + v[..., None] * up  # points on the plane through the target
    d = -np.array([0.0, 1, 1]) / np.sqrt(2)
    t = -o[..., 1] / d[1]
    x = o + t[..., None] * d  # on the floor (y = 0)
    to_c = np.array([0, h, 0]) - x
    D = np.linalg.norm(to_c, axis=-1)
    cos_t = to_c[..., 1] / D
    want = albedo * (1 - (R / D) ** 2 * cos_t)
    want = want.reshape(n, s, n, s).mean(axis=(1, 3))
    assert abs(img.mean() - want.mean()) < 2e-3 * want.mean()
    np.testing.assert_allclose(img, want, rtol=0.03)
    assert want.min() < 0.9 * albedo  # the shadow is in the test
