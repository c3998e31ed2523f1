"""Radiometry of the renderer against closed forms: area and point lights on a Lambertian
floor, soft shadows of a straight edge, anti-aliased silhouettes, mirrors and one-sided
emitters.

Every expected value is computed here, independently of the renderer: a NumPy pinhole camera
(vertical `fov`, pixel x right, y down; checked against `sssjax.camera.project`), ray-plane
intersections, and the closed-form form factor from a point to a parallel rectangle. Expected
pixel values are averaged over each pixel's footprint (a `SUB x SUB` grid of sub-pixel rays),
so they are exact up to a negligible quadrature error and the comparison is limited only by
the renderer's Monte Carlo noise; each tolerance below is derived from that noise.

Units: mm. Radiance of a Lambertian surface: `albedo / pi * E`.
"""

import math

import jax
import numpy as np
import pytest

import sssjax
from sssjax.camera import project
from sssjax.render import Renderer
from sssjax.sampling import jittered_grid, stratified_2d
from sssjax.scene import Camera

SUB = 8  # sub-pixel rays per axis for the footprint average of the expected values

FLOOR = {
    "type": "quadmesh",
    "material": "floor",
    "vertices": [[-2000, 0, -2000], [-2000, 0, 2000], [2000, 0, 2000], [2000, 0, -2000]],
    "faces": [[0, 1, 2, 3]],
}


def make_scene(camera, lights, materials, shapes, **render):
    r = {"spp": 16, "light_samples": 4, "max_depth": 0, "background": 0.0, **render}
    return sssjax.load_scene(
        {
            "camera": camera,
            "render": r,
            "sss": {"enabled": False},
            "lights": lights,
            "materials": materials,
            "shapes": shapes,
        }
    )


def quad(x0, x1, y0, y1, z0, z1, material):
    """An axis-aligned rectangle: one of the three ranges must be degenerate."""
    if y0 == y1:
        v = [[x0, y0, z0], [x0, y0, z1], [x1, y0, z1], [x1, y0, z0]]
    elif z0 == z1:
        v = [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]]
    else:
        v = [[x0, y0, z0], [x0, y1, z0], [x0, y1, z1], [x0, y0, z1]]
    return {"type": "quadmesh", "material": material, "vertices": v, "faces": [[0, 1, 2, 3]]}


# --- reference camera and closed forms ------------------------------------------------------
def reference_rays(cam: dict, sub: int = SUB):
    """Origin and unit directions `(H, W, sub*sub, 3)` of a `sub x sub` grid of rays per pixel
    (a pinhole with vertical `fov`, pixel x right, y down), written from the documented
    convention, not from `sssjax.camera`."""
    o = np.asarray(cam["origin"], float)
    fwd = np.asarray(cam["target"], float) - o
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(cam.get("up", [0.0, 1.0, 0.0]), float))
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    W, H = cam["width"], cam["height"]
    th = math.tan(math.radians(cam["fov"]) / 2)
    off = (np.arange(sub) + 0.5) / sub
    x = np.arange(W)[None, :, None, None] + off[None, None, None, :]
    y = np.arange(H)[:, None, None, None] + off[None, None, :, None]
    x, y = np.broadcast_arrays(x, y)
    sx = (2 * x / W - 1) * th * W / H
    sy = (1 - 2 * y / H) * th
    d = fwd + sx[..., None] * right + sy[..., None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return o, d.reshape(H, W, sub * sub, 3)


def hit_plane(o, d, axis: int, value: float):
    """Ray parameter and point where `o + t d` meets the plane `p[axis] = value`."""
    t = (value - o[..., axis]) / d[..., axis]
    return t, o + t[..., None] * d


def form_factor_corner(X, Y):
    """Differential area below a corner of a `X x Y` rectangle at unit height (X, Y may be
    negative: the expression is odd in each)."""
    a, b = np.sqrt(1 + X * X), np.sqrt(1 + Y * Y)
    return (X / a * np.arctan(Y / a) + Y / b * np.arctan(X / b)) / (2 * np.pi)


def form_factor_rect(p, q, p0, p1, q0, q1, d):
    """Form factor from a differential area at in-plane coordinates `(p, q)` to the parallel
    rectangle `[p0, p1] x [q0, q1]` at distance `d` (signed sum of four corner rectangles)."""

    def F(a, b):
        return form_factor_corner(a / d, b / d)

    return F(p1 - p, q1 - q) - F(p0 - p, q1 - q) - F(p1 - p, q0 - q) + F(p0 - p, q0 - q)


def plain_mc_sd(x, n, light, count=4000, seed=1):
    """Standard deviation of one-sample estimates `A L cos cos / r^2` of the irradiance at the
    points `x` `(..., 3)` (normal `n`) from an unoccluded area light `(corner, edge_u, edge_v,
    radiance)` whose point is drawn uniformly: the plain Monte Carlo error of one shadow
    sample, shape `(...)`. Stratified (jittered) sampling can only lower it."""
    c, eu, ev, L = (np.asarray(v, float) for v in light)
    u = np.random.default_rng(seed).random((count, 2))
    y = c + u[:, :1] * eu + u[:, 1:] * ev  # (count, 3)
    w = y - np.asarray(x, float)[..., None, :]
    r2 = np.sum(w * w, -1)
    w /= np.sqrt(r2)[..., None]
    nl = np.cross(eu, ev)
    A = np.linalg.norm(nl)
    g = np.maximum(w @ np.asarray(n, float), 0) * np.maximum(-(w @ (nl / A)), 0) / r2
    return np.std(A * L * g, axis=-1)


# --- the reference camera agrees with the renderer's documented projection --------------
def test_reference_camera_matches_project():
    cam = {"origin": [3.0, 40.0, 30.0], "target": [1.0, 0.0, -2.0], "fov": 7.0}
    cam.update(width=12, height=6)
    o, d = reference_rays(cam, sub=2)
    _, p = hit_plane(o, d, 1, 0.0)
    camera = Camera(
        **{k: np.asarray(v, float) if isinstance(v, list) else v for k, v in cam.items()}
    )
    got = np.asarray(project(camera, p.reshape(-1, 3))).reshape(6, 12, 4, 2)
    off = np.array([0.25, 0.75])
    want_x = np.arange(12)[None, :, None] + np.tile(off, 2)[None, None, :]
    want_y = np.arange(6)[:, None, None] + np.repeat(off, 2)[None, None, :]
    np.testing.assert_allclose(got[..., 0], np.broadcast_to(want_x, (6, 12, 4)), atol=2e-3)
    np.testing.assert_allclose(got[..., 1], np.broadcast_to(want_y, (6, 12, 4)), atol=2e-3)


# --- 1. area light over a Lambertian floor ------------------------------------------------
def test_area_light_irradiance_matches_form_factor():
    """A 40 x 20 mm light at height 50 mm over a floor of albedo rho: the radiance of a floor
    point is rho / pi * E with E = pi L F (F: point to parallel rectangle, closed form)."""
    d, w, h = 50.0, 40.0, 20.0
    L = np.array([1.0, 2.0, 3.0])
    rho = np.array([0.2, 0.5, 0.8])
    spp, n = 16, 4
    cam = {"origin": [0.0, 40.0, 30.0], "target": [0.0, 0.0, 0.0], "fov": 2.0}
    cam.update(width=8, height=8)
    light = {"type": "area", "corner": [-w / 2, d, -h / 2], "edge_u": [w, 0, 0]}
    light.update(edge_v=[0, 0, h], radiance=L.tolist())
    scene = make_scene(
        cam,
        [light],
        {"floor": {"type": "diffuse", "albedo": rho.tolist()}},
        [FLOOR],
        spp=spp,
        light_samples=n,
    )
    img = sssjax.render(scene, 0).astype(np.float64)

    o, dirs = reference_rays(cam)
    _, p = hit_plane(o, dirs, 1, 0.0)
    F = form_factor_rect(p[..., 0], p[..., 2], -w / 2, w / 2, -h / 2, h / 2, d).mean(-1)
    want = rho * L * F[..., None]  # rho / pi * (pi L F)
    # sanity of the closed form: below the centre, 4 corner rectangles of 20 x 10 at 50
    F0 = 4 * form_factor_corner(20 / 50, 10 / 50)
    assert abs(F0 - form_factor_rect(0, 0, -20, 20, -10, 10, 50)) < 1e-12
    assert np.all(np.abs(F / F0 - 1) < 0.01)  # the view is centred below the light

    # Monte Carlo bound: spp * n^2 = 256 shadow samples per pixel; one plain-MC sample has
    # a relative spread of about 0.09, jittered strata only lower it: SE <= 0.55 % per pixel.
    # Tolerance 4 SE per pixel (about 2.2 %) and 4 SE / 8 on the mean of the 64 independent
    # pixels (about 0.3 %), plus 1e-4 relative for float32.
    sd = plain_mc_sd(p.mean(-2), [0, 1, 0], ([-w / 2, d, -h / 2], [w, 0, 0], [0, 0, h], 1.0))
    se = rho * L / np.pi * sd[..., None] / math.sqrt(spp * n * n)  # (8, 8, 3)
    assert np.all(se / want < 0.006)
    err = img - want
    assert np.all(np.abs(err) <= 4 * se + 1e-4 * want), np.abs(err / want).max()
    mean_err = np.abs(err.mean(axis=(0, 1)))
    mean_tol = 4 * se.mean(axis=(0, 1)) / 8 + 1e-4 * want.mean(axis=(0, 1))
    assert np.all(mean_err <= mean_tol), (mean_err, mean_tol)


# --- 2. point light --------------------------------------------------------------------
def test_point_light_inverse_square_and_cosine():
    """A point light of intensity I at height 40 mm: the floor at horizontal offset x has
    radiance rho / pi * I cos(theta) / r^2 = rho / pi * I h / r^3. Deterministic up to the
    pixel footprint (averaged in the expected value too): tolerance 0.5 % per pixel."""
    hgt = 40.0
    I = np.array([1000.0, 2000.0, 500.0])
    rho = np.array([0.7, 0.3, 0.5])
    cam = {"origin": [25.0, 30.0, 40.0], "target": [25.0, 0.0, 0.0], "fov": 3.0}
    cam.update(width=8, height=8)
    scene = make_scene(
        cam,
        [{"type": "point", "position": [0.0, hgt, 0.0], "intensity": I.tolist()}],
        {"floor": {"type": "diffuse", "albedo": rho.tolist()}},
        [FLOOR],
        spp=4,
        light_samples=1,
    )
    img = sssjax.render(scene, 0).astype(np.float64)
    o, dirs = reference_rays(cam)
    _, p = hit_plane(o, dirs, 1, 0.0)
    r = np.sqrt(p[..., 0] ** 2 + p[..., 2] ** 2 + hgt**2)
    want = rho / np.pi * I * (hgt / r**3).mean(-1)[..., None]
    # the view is centred at 25 mm from the foot of the light: cos(theta) = 40 / 47.2
    assert np.allclose(want / (rho / np.pi * I * hgt / (25**2 + hgt**2) ** 1.5), 1, atol=0.06)
    np.testing.assert_allclose(img, want, rtol=5e-3)


# --- 3. soft shadow of a straight edge ---------------------------------------------------
def test_penumbra_of_straight_edge():
    """A 40 x 30 light (x in [-20, 20], z in [-15, 15]) at height H = 50 over the floor, and
    a black half-plane occluder {x < 0} at height h = 25. A floor point at x = px sees the
    light points with lx > b(px) = px + (0 - px) H / h = -px, so its irradiance is pi L times
    the form factor of the sub-rectangle [max(-20, -px), 20] x [-15, 15]; the penumbra spans
    px in [-20, 20]. A row of pixels across it, averaged over 4 seeds."""
    H, h, xe = 50.0, 25.0, 0.0
    x0, x1, z0, z1 = -20.0, 20.0, -15.0, 15.0
    L, rho = 2.0, 0.8
    spp, n, seeds = 64, 4, 4
    cam = {"origin": [0.0, 20.0, 60.0], "target": [0.0, 0.0, 0.0], "fov": 5.5}
    cam.update(width=32, height=4)
    light = {"type": "area", "corner": [x0, H, z0], "edge_u": [x1 - x0, 0, 0]}
    light.update(edge_v=[0, 0, z1 - z0], radiance=L)
    scene = make_scene(
        cam,
        [light],
        {
            "floor": {"type": "diffuse", "albedo": rho},
            "black": {"type": "diffuse", "albedo": 0.0},
        },
        [FLOOR, quad(-1000.0, xe, h, h, -1000.0, 1000.0, "black")],
        spp=spp,
        light_samples=n,
    )
    r = Renderer(scene)
    imgs = np.stack([r.render(s, (), False)[..., 0] for s in range(seeds)]).astype(np.float64)

    o, dirs = reference_rays(cam)
    _, p = hit_plane(o, dirs, 1, 0.0)
    assert np.all(p[..., 1] < h)  # the camera rays pass below the occluder
    px, pz = p[..., 0], p[..., 2]
    b = np.clip(px + (xe - px) * H / h, x0, x1)
    F = form_factor_rect(px, pz, b, x1, z0, z1, H).mean(-1)
    want = rho * L * F
    full = rho * L * form_factor_rect(px, pz, x0, x1, z0, z1, H).mean(-1)
    pen = (want > 0.02 * full) & (want < 0.98 * full)
    assert pen.sum() >= 40  # the row covers the penumbra, plus umbra and full light
    assert (want == 0).sum() >= 4 and (want > 0.999 * full).sum() >= 4

    # The shadow boundary on the light is a line of constant u, crossing one column of n
    # strata; each is a Bernoulli sample of variance p (1 - p) <= 1/4 and weight at most
    # A L / (n^2 H^2) (the geometry term cos cos / r^2 <= 1 / H^2); the other strata see a
    # smooth integrand. So SE per pixel <= rho / pi * A L / (n^2 H^2) * sqrt(n / 4 / spp):
    # about 0.9 % of the fully lit value; over 4 seeds half that. Tolerance 3 SE (+ 0.3 % of
    # the fully lit value for the smooth part) per pixel.
    A = (x1 - x0) * (z1 - z0)
    se1 = rho / np.pi * A * L / (n * n * H * H) * math.sqrt(n / 4 / spp)
    mean = imgs.mean(0)
    tol = 3 * se1 / math.sqrt(seeds) + 3e-3 * full
    bad = np.abs(mean - want) > tol
    assert not bad.any(), (np.argwhere(bad), (mean - want)[bad], tol[bad])
    # the spread over seeds in the penumbra agrees with that bound
    sd = np.sqrt(np.mean(imgs[:, pen].var(0, ddof=1)))
    assert sd <= se1, (sd, se1)
    # the umbra is exactly black
    assert np.all(imgs[:, want == 0] == 0)


def test_jittered_grid_one_point_per_cell():
    n = 5
    pts = np.asarray(jittered_grid(jax.random.key(3), n, (3, 2)))
    assert pts.shape == (3, 2, n * n, 2)
    assert np.all((pts >= 0) & (pts < 1))
    cells = np.floor(pts * n).astype(int)
    k = np.arange(n * n)
    # cell-major order: point k lies in cell (k // n, k % n), hence one point per cell
    assert np.all(cells[..., 0] == k // n) and np.all(cells[..., 1] == k % n)
    # the jitter within the cells is not degenerate and differs between batch elements
    frac = (pts * n - cells).reshape(-1, 2)
    assert frac.std(0).min() > 0.2
    assert not np.allclose(pts[0, 0], pts[1, 0])
    # stratified_2d with a square count is that grid
    s2 = np.asarray(stratified_2d(jax.random.key(4), 16, (7,)))
    c2 = np.floor(s2 * 4).astype(int)
    assert {tuple(c) for c in c2[3]} == {(i, j) for i in range(4) for j in range(4)}


# --- 4. anti-aliasing ------------------------------------------------------------------
def test_antialiased_silhouette_converges_to_coverage():
    """A black (albedo 0) quad covering the world quadrant {x < xe, y < ye} of the plane
    z = 0, seen head-on against a background of 1: a pixel's value is 1 minus the fraction of
    it the quad covers, from the edges' sub-pixel positions given by `project`.

    spp = 64 (an 8 x 8 jittered grid): a straight edge crosses one column (or row) of 8
    strata, each a Bernoulli sample: SE <= sqrt(8 / 4) / 64 = 0.022 per edge pixel. Tolerance
    0.08 (3.6 SE) per pixel, 0.02 on the mean along each edge (20 pixels: SE <= 0.005)."""
    W = Hh = 24
    spp = 64
    xe, ye = 6.1, 6.13
    cam = {"origin": [0.0, 0.0, 100.0], "target": [0.0, 0.0, 0.0], "fov": 10.0}
    cam.update(width=W, height=Hh)
    scene = make_scene(
        cam,
        [],
        {"black": {"type": "diffuse", "albedo": 0.0}},
        [quad(-1000.0, xe, -1000.0, ye, 0.0, 0.0, "black")],
        spp=spp,
        light_samples=1,
        background=1.0,
    )
    img = sssjax.render(scene, 0).astype(np.float64)
    assert np.allclose(img[..., 0], img[..., 1]) and np.allclose(img[..., 0], img[..., 2])
    img = img[..., 0]
    ex, ey = np.asarray(project(scene.camera, np.array([[xe, ye, 0.0]])))[0]
    assert 0.2 < ex % 1 < 0.8 and 0.2 < ey % 1 < 0.8  # both edges cut pixels
    assert int(ex) >= 20 and Hh - int(ey) - 1 >= 20  # 20 pixels along each edge
    fx = np.clip(ex - np.arange(W), 0, 1)  # covered part of each column (left of the edge)
    fy = np.clip(np.arange(Hh) + 1 - ey, 0, 1)  # covered part of each row (below the edge)
    want = 1 - fy[:, None] * fx[None, :]
    assert np.abs(img - want).max() <= 0.08, np.abs(img - want).max()
    ix, iy = int(ex), int(ey)
    exact = np.abs(want - 0.5) == 0.5
    assert np.array_equal(img[exact], want[exact])  # fully covered or free pixels are exact
    col = img[iy + 1 :, ix]  # the vertical edge, below the horizontal one
    row = img[iy, :ix]  # the horizontal edge, left of the vertical one
    assert abs(col.mean() - (1 - (ex % 1))) <= 0.02, col.mean()
    assert abs(row.mean() - (1 - (1 - ey % 1))) <= 0.02, row.mean()


# --- 5. mirrors ------------------------------------------------------------------------
R_MIRROR = [0.9, 0.6, 0.3]
BG = [0.5, 1.0, 2.0]


def corridor_bounces(s, a=10.0, length=100.0):
    """Reflections of a ray of horizontal slope `s = dx / d(-z)` from x = 0 between mirrors
    at x = +-a before it leaves the corridor at depth `length` (unfolded: walls at
    |x| = a, 3a, 5a, ...)."""
    return np.floor((np.abs(s) * length + a) / (2 * a)).astype(int)


@pytest.mark.parametrize("depth", [0, 1, 3])
def test_facing_mirrors_decay_as_r_to_the_k(depth):
    """The camera looks down a corridor between two facing mirrors (x = +-10 mm, 100 mm
    deep) at a uniform background: a pixel whose rays reflect k times shows R^k times the
    background when k <= max_depth, and black when the path is cut off (max_depth = 0: the
    mirrors are black). Deterministic (no lights): tolerance float32 round-off."""
    a, length = 10.0, 100.0
    W, th = 32, 0.8  # horizontal tan(half fov)
    cam = {"origin": [0.0, 0.0, 0.0], "target": [0.0, 0.0, -1.0], "width": W, "height": 2}
    cam["fov"] = math.degrees(2 * math.atan(th * 2 / W))
    shapes = [
        quad(-a, -a, -1000.0, 1000.0, -length, 50.0, "mirror"),
        quad(a, a, -1000.0, 1000.0, -length, 50.0, "mirror"),
    ]
    scene = make_scene(
        cam,
        [],
        {"mirror": {"type": "mirror", "reflectance": R_MIRROR}},
        shapes,
        spp=4,
        light_samples=1,
        max_depth=depth,
        background=BG,
    )
    img = sssjax.render(scene, 0).astype(np.float64)
    edges = (2 * np.arange(W + 1) / W - 1) * th  # slopes at the pixel columns' edges
    k_lo, k_hi = corridor_bounces(edges[:-1]), corridor_bounces(edges[1:])
    same = k_lo == k_hi
    assert same.sum() >= 20 and set(k_lo[same]) >= {0, 1, 2, 3, 4}
    k = k_lo
    want = np.where((k <= depth)[:, None], np.power.outer(np.array(R_MIRROR), k).T * BG, 0.0)
    for j in np.flatnonzero(same):
        np.testing.assert_allclose(
            img[:, j],
            np.broadcast_to(want[j], (2, 3)),
            rtol=1e-5,
            atol=1e-7,
            err_msg=f"column {j}, k={k[j]}",
        )


def test_mirror_reflects_lit_diffuse_floor():
    """A point-lit floor seen directly and in a vertical mirror (reflectance R) at z = -30: a
    pixel whose rays all reach the floor through the mirror shows R times the radiance of the
    floor point they reach, rho / pi * I h / r^3 (computed by reflecting the rays here).
    Deterministic up to the footprint: tolerance 0.5 %."""
    hgt, zm = 40.0, -30.0
    I, rho = 3000.0, 0.6
    cam = {"origin": [0.0, 30.0, 30.0], "target": [0.0, 0.0, zm], "fov": 8.0}
    cam.update(width=12, height=12)
    scene = make_scene(
        cam,
        [{"type": "point", "position": [0.0, hgt, 0.0], "intensity": I}],
        {
            "floor": {"type": "diffuse", "albedo": rho},
            "mirror": {"type": "mirror", "reflectance": R_MIRROR},
        },
        [FLOOR, quad(-200.0, 200.0, 0.0, 200.0, zm, zm, "mirror")],
        spp=16,
        light_samples=1,
        max_depth=1,
    )
    img = sssjax.render(scene, 0).astype(np.float64)
    o, d = reference_rays(cam)
    t_f, _ = hit_plane(o, d, 1, 0.0)
    t_f = np.where(t_f > 0, t_f, np.inf)
    t_m, pm = hit_plane(o, d, 2, zm)
    via = (t_m > 0) & (t_m < t_f) & (pm[..., 1] > 0)
    d2 = d * np.array([1.0, 1.0, -1.0])  # reflected at the plane z = zm
    _, p2 = hit_plane(pm, d2, 1, 0.0)
    _, p1 = hit_plane(o, d, 1, 0.0)
    p = np.where(via[..., None], p2, p1)

    def radiance(q):
        r = np.sqrt(q[..., 0] ** 2 + (q[..., 2]) ** 2 + hgt**2)
        return rho / np.pi * I * hgt / r**3

    R = np.array(R_MIRROR)
    factor = np.where(via[..., None], R, 1.0)  # (H, W, S, 3)
    want = (factor * radiance(p)[..., None]).mean(-2)
    all_via, none_via = via.all(-1), ~via.any(-1)
    assert all_via.sum() >= 40 and none_via.sum() >= 20
    np.testing.assert_allclose(img[all_via], want[all_via], rtol=5e-3)
    np.testing.assert_allclose(img[none_via], want[none_via], rtol=5e-3)
    # and the ratio to the unreflected radiance is R, channel by channel
    ratio = img[all_via] / radiance(p).mean(-1)[all_via][:, None]
    np.testing.assert_allclose(ratio, np.broadcast_to(R, ratio.shape), rtol=5e-3)


# --- 6. one-sided area lights ----------------------------------------------------------
def test_area_light_one_sided():
    """Two 10 x 10 area lights in the plane z = 0 seen head-on from z = +100: A faces the
    camera and shows its radiance; B faces away (towards a diffuse backdrop at z = -20) and is
    black from the camera. The backdrop is lit by B only (A emits away from it): radiance
    rho L_B F, F the form factor to the parallel rectangle B at distance 20."""
    LA, LB = np.array([1.0, 2.0, 3.0]), np.array([4.0, 4.0, 4.0])
    rho, zb = 0.5, -20.0
    spp, n = 16, 4
    cam = {"origin": [0.0, 0.0, 100.0], "target": [0.0, 0.0, 0.0], "fov": 20.0}
    cam.update(width=24, height=16)
    lights = [
        {"type": "area", "corner": [-12.0, -5.0, 0.0], "edge_u": [10.0, 0, 0]},
        {"type": "area", "corner": [2.0, -5.0, 0.0], "edge_u": [0, 10.0, 0]},
    ]
    lights[0].update(edge_v=[0, 10.0, 0], radiance=LA.tolist())  # u x v = +z: to the camera
    lights[1].update(edge_v=[10.0, 0, 0], radiance=LB.tolist())  # u x v = -z: away
    scene = make_scene(
        cam,
        lights,
        {"wall": {"type": "diffuse", "albedo": rho}},
        [quad(-500.0, 500.0, -500.0, 500.0, zb, zb, "wall")],
        spp=spp,
        light_samples=n,
        background=0.25,
    )
    img = sssjax.render(scene, 0).astype(np.float64)
    o, d = reference_rays(cam)
    _, p0 = hit_plane(o, d, 2, 0.0)
    in_a = (p0[..., 0] > -12) & (p0[..., 0] < -2) & (np.abs(p0[..., 1]) < 5)
    in_b = (p0[..., 0] > 2) & (p0[..., 0] < 12) & (np.abs(p0[..., 1]) < 5)
    a_px, b_px = in_a.all(-1), in_b.all(-1)
    wall_px = ~(in_a | in_b).any(-1)
    assert a_px.sum() >= 10 and b_px.sum() >= 10 and wall_px.sum() >= 100
    np.testing.assert_allclose(img[a_px], np.broadcast_to(LA, img[a_px].shape), rtol=1e-6)
    assert np.all(img[b_px] == 0)

    _, pw = hit_plane(o, d, 2, zb)
    F = form_factor_rect(pw[..., 0], pw[..., 1], 2.0, 12.0, -5.0, 5.0, -zb).mean(-1)
    want = rho * LB * F[..., None]
    # plain-MC bound of one shadow sample at each pixel's mean backdrop point; 256 samples
    # per pixel; tolerance 4 SE plus 2e-3 of the peak (float32, and the variation of that
    # bound over the pixel footprint)
    sd = plain_mc_sd(pw.mean(-2), [0, 0, 1], ([2, -5, 0], [0, 10, 0], [10, 0, 0], 1.0))
    se = rho * LB / np.pi * sd[..., None] / math.sqrt(spp * n * n)
    tol = (4 * se + 2e-3 * want.max())[wall_px]
    err = np.abs(img[wall_px] - want[wall_px])
    assert np.all(err <= tol), (err / tol).max()
    # A would add this much if it lit the backdrop (were it two-sided): far above tolerance
    FA = form_factor_rect(pw[..., 0], pw[..., 1], -12.0, -2.0, -5.0, 5.0, -zb).mean(-1)
    assert (rho * LA * FA[..., None])[wall_px].max() > 10 * tol.max()
