"""Shapes: hits against hand-computed answers, exact areas, uniform sampling, tessellation, OBJ.

Every expected number here is worked out by hand (or from a closed form), never taken from the
code under test.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from sssjax.shapes import (
    Cone,
    Cube,
    Cylinder,
    QuadMesh,
    Sphere,
    intersect_all,
    load_obj,
    make_shape,
    placement,
)

S5 = math.sqrt(5.0)
S2 = math.sqrt(2.0)
S3 = math.sqrt(3.0)

# The unit cube [0, 1]^3 as quads wound counter-clockwise seen from outside.
CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    float,
)
CUBE_F = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [0, 4, 7, 3], [1, 2, 6, 5]]

# A square pyramid: quad base [-1, 1]^2 at y = 0 (facing -y) and four triangles to (0, 1, 0).
PYR_V = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1], [0, 1, 0]], float)
PYR_F = [[0, 1, 2, 3], [0, 4, 1], [1, 4, 2], [2, 4, 3], [3, 4, 0]]


def pyramid(**kw):
    return QuadMesh(PYR_V, PYR_F, **kw)


def unit_cube_mesh(**kw):
    return QuadMesh(CUBE_V, CUBE_F, **kw)


def _placed(cls, *args, translate=(0, 0, 0), rotate=(0, 0, 0), scale=1.0):
    w, o = placement(translate, rotate, scale)
    return cls(*args, to_world=w, to_object=o)


N_PAD = 16  # small ray batches are padded to one size so that their compilation is shared


def _cast(shape, rays, **kw):
    """Intersect a short list of `(o, d)` rays, padded to `N_PAD` rays."""
    o = np.asarray([r[0] for r in rays], float)
    d = np.asarray([r[1] for r in rays], float)
    k = len(rays)
    pad = np.arange(N_PAD) % k
    t, n = shape.intersect(o[pad], d[pad], **kw)
    return np.asarray(t)[:k], np.asarray(n)[:k]


def _hit(shape, o, d, **kw):
    t, n = _cast(shape, [(o, d)], **kw)
    return float(t[0]), n[0]


# --- placement ----------------------------------------------------------------------------
def test_placement_order_and_inverse():
    # S then Rz(90) then T: (1,0,0) -> (2,0,0) -> (0,2,0) -> (1,4,3)
    w, o = placement(translate=(1, 2, 3), rotate=(0, 0, 90), scale=2.0)
    np.testing.assert_allclose(w @ [1, 0, 0, 1], [1, 4, 3, 1], atol=1e-12)
    np.testing.assert_allclose(w @ o, np.eye(4), atol=1e-12)
    # x first, then y: Rx(90) takes e_y to e_z and Ry(90) takes e_z to e_x.
    w, _ = placement(rotate=(90, 90, 0))
    np.testing.assert_allclose(w[:3, :3] @ [0, 1, 0], [1, 0, 0], atol=1e-12)
    # ... and not the other way round (Ry first would leave e_y, then Rx gives e_z).
    w, _ = placement(rotate=(30, 0, 0))
    c30, s30 = math.cos(math.radians(30)), math.sin(math.radians(30))
    np.testing.assert_allclose(w[:3, :3] @ [0, 1, 0], [0, c30, s30], atol=1e-12)
    w, o = placement(scale=(1, 2, 4))
    np.testing.assert_allclose(np.diag(w), [1, 2, 4, 1])
    np.testing.assert_allclose(np.diag(o), [1, 0.5, 0.25, 1])
    with pytest.raises(ValueError, match="non-zero"):
        placement(scale=(1, 0, 1))


# --- hits and misses, object space -----------------------------------------------------------
HITS = [
    # (id, shape factory, origin, direction, t, normal)
    ("sphere-front", lambda: Sphere(2.0), (0, 0, -5), (0, 0, 1), 3.0, (0, 0, -1)),
    ("sphere-nonunit-d", lambda: Sphere(2.0), (0, 0, -5), (0, 0, 2), 1.5, (0, 0, -1)),
    ("sphere-offaxis", lambda: Sphere(2.0), (1, 0, -5), (0, 0, 1), 5 - S3, (0.5, 0, -S3 / 2)),
    ("box-x", lambda: Cube((2, 4, 6)), (-5, 0.5, 0.5), (1, 0, 0), 4.0, (-1, 0, 0)),
    ("box-top", lambda: Cube((2, 4, 6)), (0.2, 10, 0.3), (0, -1, 0), 8.0, (0, 1, 0)),
    ("box-z", lambda: Cube((2, 4, 6)), (0.1, 0.1, -10), (0, 0, 1), 7.0, (0, 0, -1)),
    ("box-oblique", lambda: Cube(2.0), (-3, -2, 0), (1, 1, 0), 2.0, (-1, 0, 0)),
    ("cyl-side", lambda: Cylinder(1.0, 2.0), (-5, 1, 0), (1, 0, 0), 4.0, (-1, 0, 0)),
    ("cyl-side-z", lambda: Cylinder(1.0, 2.0), (0.6, 1.5, 5), (0, 0, -1), 4.2, (0.6, 0, 0.8)),
    ("cyl-top-cap", lambda: Cylinder(1.0, 2.0), (0.3, 5, 0.2), (0, -1, 0), 3.0, (0, 1, 0)),
    ("cyl-bottom-cap", lambda: Cylinder(1.0, 2.0), (0.3, -4, -0.5), (0, 1, 0), 4.0, (0, -1, 0)),
    ("cyl-cap-oblique", lambda: Cylinder(1.0, 2.0), (0, 3, 0), (0.5, -1, 0), 1.0, (0, 1, 0)),
    ("cone-side", lambda: Cone(1.0, 2.0), (-5, 1, 0), (1, 0, 0), 4.5, (-2 / S5, 1 / S5, 0)),
    ("cone-side-top", lambda: Cone(1.0, 2.0), (0.25, 5, 0), (0, -1, 0), 3.5, (2 / S5, 1 / S5, 0)),
    ("cone-base-cap", lambda: Cone(1.0, 2.0), (0.2, -3, 0.1), (0, 1, 0), 3.0, (0, -1, 0)),
    ("mesh-cube-x", unit_cube_mesh, (-1, 0.5, 0.25), (1, 0, 0), 1.0, (-1, 0, 0)),
    ("mesh-cube-top", unit_cube_mesh, (0.3, 4, 0.6), (0, -1, 0), 3.0, (0, 1, 0)),
    ("pyramid-side", pyramid, (0, 0.5, -5), (0, 0, 1), 4.5, (0, 1 / S2, -1 / S2)),
    ("pyramid-base", pyramid, (0.3, -2, 0.1), (0, 1, 0), 2.0, (0, -1, 0)),
]

MISSES = [
    ("sphere-beside", lambda: Sphere(2.0), (0, 2.5, -5), (0, 0, 1)),
    ("sphere-behind", lambda: Sphere(2.0), (0, 0, -5), (0, 0, -1)),
    ("box-beside", lambda: Cube((2, 4, 6)), (-5, 2.5, 0), (1, 0, 0)),
    ("cyl-above", lambda: Cylinder(1.0, 2.0), (-5, 2.5, 0), (1, 0, 0)),  # hits infinite cyl.
    ("cyl-below", lambda: Cylinder(1.0, 2.0), (-5, -0.5, 0), (1, 0, 0)),
    ("cone-upper-nappe", lambda: Cone(1.0, 2.0), (-5, 3, 0), (1, 0, 0)),  # x^2 = k^2 (H-y)^2
    ("cone-below-base", lambda: Cone(1.0, 2.0), (-5, -1, 0), (1, 0, 0)),
    ("cone-beside", lambda: Cone(1.0, 2.0), (-5, 1, 0.6), (1, 0, 0)),  # radius 0.5 at y=1
    ("mesh-beside", unit_cube_mesh, (-1, 1.5, 0.5), (1, 0, 0)),
    ("pyramid-corner", pyramid, (0.9, 0.9, -5), (0, 0, 1)),  # above the slanted face
]


@pytest.mark.parametrize("case", HITS, ids=[c[0] for c in HITS])
def test_hit_against_hand_computed(x64, case):
    _, make, o, d, t_exp, n_exp = case
    t, n = _hit(make(), o, d)
    assert t == pytest.approx(t_exp, abs=1e-10)
    np.testing.assert_allclose(n, n_exp, atol=1e-10)


@pytest.mark.parametrize("case", MISSES, ids=[c[0] for c in MISSES])
def test_miss(x64, case):
    _, make, o, d = case
    t, n = _hit(make(), o, d)
    assert t == np.inf
    np.testing.assert_array_equal(n, 0.0)


def test_t_window(x64):
    s = Sphere(2.0)
    assert _hit(s, (0, 0, -5), (0, 0, 1), t_max=2.9)[0] == np.inf
    assert _hit(s, (0, 0, -5), (0, 0, 1), t_min=3.1)[0] == pytest.approx(7.0)  # the exit
    # per-ray windows broadcast against the rays
    o, d = np.tile([0.0, 0, -5], (N_PAD, 1)), np.tile([0.0, 0, 1], (N_PAD, 1))
    t, _ = s.intersect(o, d, t_min=np.tile([0.0, 3.5], N_PAD // 2))
    np.testing.assert_allclose(t[:4], [3.0, 7.0, 3.0, 7.0])


INSIDE = [
    ("sphere", lambda: Sphere(2.0), (0, 0, 0), (1, 0, 0), 2.0, (1, 0, 0)),
    ("sphere-off", lambda: Sphere(2.0), (0, 1, 0), (0, 0, -3), S3 / 3, (0, 0.5, -S3 / 2)),
    ("box", lambda: Cube((2, 4, 6)), (0, 0, 0), (0, 1, 0), 2.0, (0, 1, 0)),
    ("box-neg", lambda: Cube((2, 4, 6)), (0.5, 0, 0), (0, 0, -1), 3.0, (0, 0, -1)),
    ("cyl-top", lambda: Cylinder(1.0, 2.0), (0, 1, 0), (0, 1, 0), 1.0, (0, 1, 0)),
    ("cyl-bottom", lambda: Cylinder(1.0, 2.0), (0, 1, 0), (0, -2, 0), 0.5, (0, -1, 0)),
    ("cyl-side", lambda: Cylinder(1.0, 2.0), (0, 1, 0), (1, 0, 0), 1.0, (1, 0, 0)),
    ("cone-base", lambda: Cone(1.0, 2.0), (0, 0.5, 0), (0, -1, 0), 0.5, (0, -1, 0)),
    ("cone-side", lambda: Cone(1.0, 2.0), (0, 0.5, 0), (1, 0, 0), 0.75, (2 / S5, 1 / S5, 0)),
    ("mesh-cube", unit_cube_mesh, (0.5, 0.5, 0.5), (0, 0, 1), 0.5, (0, 0, 1)),
    ("pyramid", pyramid, (0, 0.25, 0), (0, 0, -1), 0.75, (0, 1 / S2, -1 / S2)),
]


@pytest.mark.parametrize("case", INSIDE, ids=[c[0] for c in INSIDE])
def test_ray_from_inside_exits_with_outward_normal(x64, case):
    _, make, o, d, t_exp, n_exp = case
    t, n = _hit(make(), o, d)
    assert t == pytest.approx(t_exp, abs=1e-10)
    np.testing.assert_allclose(n, n_exp, atol=1e-10)


# --- grazing rays and gradients ---------------------------------------------------------------
GRAZING = {
    "sphere": (
        lambda: Sphere(2.0),
        [((-5, 2, 0), (1, 0, 0)), ((0, -3, 2), (0, 1, 0)), ((-3, 0, 0), (0, 0, 0))],
    ),
    "box": (
        lambda: Cube((2, 4, 6)),
        [((-5, 2, 0), (1, 0, 0)), ((-5, 2, 3), (1, 0, 0)), ((0, 0, -5), (0, 0, 1))],
    ),
    "cylinder": (
        lambda: Cylinder(1.0, 2.0),
        [((1, -5, 0), (0, 1, 0)), ((-5, 1, 1), (1, 0, 0)), ((-5, 2, 0), (1, 0, 0))],
    ),
    "cone": (
        lambda: Cone(1.0, 2.0),
        [((4, -6, 0), (-1, 2, 0)), ((0, 5, 0), (0, -1, 0)), ((-5, 0, 0), (1, 0, 0))],
    ),
    "mesh-cube": (
        unit_cube_mesh,
        [((-1, 0, 0.5), (1, 0, 0)), ((-1, 0.5, 1.5), (1, 0, -1)), ((-1, 0.5, 0.5), (0, 0, 0))],
    ),
    "pyramid": (
        pyramid,
        [((0, 1, -5), (0, 0, 1)), ((-5, 0, 0), (1, 0, 0)), ((-2, -1, -2), (1, 1, 1))],
    ),
}


@pytest.mark.parametrize("name", sorted(GRAZING))
def test_grazing_and_random_rays_are_nan_free_with_gradients(name):
    """Tangent rays, rays in a face or cap plane, along a generator or through the apex, zero
    directions, plus random rays from inside and outside: finite values and gradients."""
    make, rays = GRAZING[name]
    shape = make()
    rng = np.random.default_rng(0)
    k, n_rays = len(rays), 64
    lo, hi = shape.bounds()
    c, e = (lo + hi) / 2, (hi - lo) / 2
    start = c + e * rng.uniform(-2, 2, (n_rays - k, 3))  # inside and outside
    aim = c + e * rng.uniform(-1.2, 1.2, (n_rays - k, 3))
    o = np.concatenate([[r[0] for r in rays], start])
    d = np.concatenate([[r[1] for r in rays], aim - start])
    o, d = jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)

    def loss(o, d):
        t, n = shape.intersect(o, d)
        return jnp.sum(jnp.where(jnp.isfinite(t), t, 0.0)) + jnp.sum(n * jnp.arange(3.0)), (t, n)

    (_, (t, n)), (go, gd) = jax.jit(jax.value_and_grad(loss, (0, 1), has_aux=True))(o, d)
    t, n = np.asarray(t), np.asarray(n)
    assert not np.any(np.isnan(t)) and not np.any(np.isnan(n))
    assert np.all(np.isfinite(go)) and np.all(np.isfinite(gd))
    hit = np.isfinite(t)
    assert 5 < hit.sum() < n_rays  # the random rays both hit and miss
    np.testing.assert_allclose(np.linalg.norm(n[hit], axis=-1), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(n[~hit], 0.0)
    assert np.all(t[hit] > 1e-4)
    # the same grazing rays in float64
    with jax.enable_x64(True):
        t64, n64 = _cast(make(), rays)
    assert not np.any(np.isnan(t64)) and not np.any(np.isnan(n64))


def test_gradient_matches_analytic(x64):
    # Sphere of radius r, ray from (x0, 0, -5) along +z: t = 5 - sqrt(r^2 - x0^2).
    s, x0 = Sphere(2.0), 1.2

    @jax.jit
    @jax.grad
    def dt_do(o):
        return s.intersect(o[None], jnp.array([[0.0, 0.0, 1.0]]))[0][0]

    g = dt_do(jnp.array([x0, 0.0, -5.0]))
    np.testing.assert_allclose(g, [x0 / math.sqrt(4 - x0**2), 0.0, -1.0], atol=1e-10)
    # Box face x = -1: t = (-1 - o_x) / d_x, so dt/dd = (-t / d_x, 0, 0).
    b = Cube(2.0)

    @jax.jit
    @jax.grad
    def dt_dd(d):
        return b.intersect(jnp.array([[-5.0, 0.1, 0.2]]), d[None])[0][0]

    np.testing.assert_allclose(dt_dd(jnp.array([2.0, 0.0, 0.0])), [-1.0, 0.0, 0.0], atol=1e-10)


# --- transformed instances -----------------------------------------------------------------------
def test_scaled_translated_sphere(x64):
    s = _placed(Sphere, 1.0, translate=(1, 2, 3), scale=2.0)  # radius 2 about (1, 2, 3)
    t, n = _hit(s, (1, 2, -10), (0, 0, 1))
    assert t == pytest.approx(11.0, abs=1e-10)
    np.testing.assert_allclose(n, [0, 0, -1], atol=1e-10)
    t, n = _hit(s, (2, 2, -10), (0, 0, 0.5))  # z = 3 - sqrt(3), parameter doubled
    assert t == pytest.approx(2 * (13 - S3), abs=1e-10)
    np.testing.assert_allclose(n, [0.5, 0, -S3 / 2], atol=1e-10)
    t, n = _hit(s, (1, 2, 3), (0, -1, 0))  # from the centre
    assert t == pytest.approx(2.0, abs=1e-10)
    np.testing.assert_allclose(n, [0, -1, 0], atol=1e-10)


def test_ellipsoid_normal_is_inverse_transpose(x64):
    # x^2 + y^2/4 + z^2/9 = 1; at y = 1, z = 0: x = -sqrt(3)/2, gradient (-sqrt3, 1/2, 0).
    s = _placed(Sphere, 1.0, scale=(1, 2, 3), rotate=(0, 0, 0))
    t, n = _hit(s, (-10, 1, 0), (1, 0, 0))
    assert t == pytest.approx(10 - S3 / 2, abs=1e-10)
    g = np.array([-S3, 0.5, 0.0])
    np.testing.assert_allclose(n, g / np.linalg.norm(g), atol=1e-10)


def test_rotated_scaled_cylinder(x64):
    # Rz(-90) takes the +y axis to +x; scale 2 and shift 1: radius 2, x from 1 to 5.
    c = _placed(Cylinder, 1.0, 2.0, translate=(1, 0, 0), rotate=(0, 0, -90), scale=2.0)
    t, n = _hit(c, (10, 0.5, 0.5), (-1, 0, 0))
    assert t == pytest.approx(5.0, abs=1e-10)
    np.testing.assert_allclose(n, [1, 0, 0], atol=1e-10)
    t, n = _hit(c, (3, 10, 0), (0, -1, 0))
    assert t == pytest.approx(8.0, abs=1e-10)
    np.testing.assert_allclose(n, [0, 1, 0], atol=1e-10)
    t, n = _hit(c, (-3, 0.2, 0.1), (1, 0, 0))  # bottom cap, x = 1
    assert t == pytest.approx(4.0, abs=1e-10)
    np.testing.assert_allclose(n, [-1, 0, 0], atol=1e-10)


def test_rotated_cube_is_a_diamond(x64):
    b = _placed(Cube, 2.0, rotate=(0, 0, 45))  # |x| + |y| <= sqrt(2) in the plane
    t, n = _hit(b, (-10, 0.5, 0), (1, 0, 0))
    assert t == pytest.approx(10 - (S2 - 0.5), abs=1e-10)
    np.testing.assert_allclose(n, [-1 / S2, 1 / S2, 0], atol=1e-10)


def test_transformed_cone_and_mesh(x64):
    # Cone flipped upside down (Rx(180)): apex at y = -2*1.5 = -3 after scale 1.5, base at 0.
    c = _placed(Cone, 1.0, 2.0, rotate=(180, 0, 0), scale=1.5, translate=(0, 0, 1))
    t, n = _hit(c, (0.3, 5, 1.2), (0, -1, 0))  # base disc at y = 0, now facing +y
    assert t == pytest.approx(5.0, abs=1e-10)
    np.testing.assert_allclose(n, [0, 1, 0], atol=1e-10)
    # Unit-cube mesh scaled (2, 3, 4) and moved: box [5, 7] x [0, 3] x [0, 4].
    m = _placed(QuadMesh, CUBE_V, CUBE_F, translate=(5, 0, 0), scale=(2, 3, 4))
    t, n = _hit(m, (6, 1, 10), (0, 0, -2))
    assert t == pytest.approx(3.0, abs=1e-10)
    np.testing.assert_allclose(n, [0, 0, 1], atol=1e-10)


def test_mirroring_placement_keeps_normals_outward(x64):
    s = _placed(QuadMesh, CUBE_V, CUBE_F, scale=(-1, 1, 1))  # box [-1, 0] x [0,1] x [0,1]
    t, n = _hit(s, (-5, 0.5, 0.5), (1, 0, 0))
    assert t == pytest.approx(4.0, abs=1e-10)
    np.testing.assert_allclose(n, [-1, 0, 0], atol=1e-10)
    v, f = s.tessellate()
    assert _signed_volume(v, f) == pytest.approx(1.0)


# --- areas ---------------------------------------------------------------------------------------
def _cone_area(r, h):
    return math.pi * r * math.sqrt(r * r + h * h) + math.pi * r * r


AREAS = [
    ("sphere", lambda: Sphere(1.5), 4 * math.pi * 1.5**2),
    ("sphere-scaled", lambda: _placed(Sphere, 1.5, scale=2, rotate=(10, 20, 30)), 36 * math.pi),
    ("cube", lambda: Cube(3.0), 54.0),
    ("box", lambda: Cube((1, 2, 3)), 22.0),
    (
        "box-nonuniform",
        lambda: _placed(Cube, (1, 2, 3), scale=(2, 1, 0.5), rotate=(0, 0, 30)),
        20.0,
    ),
    ("cylinder", lambda: Cylinder(0.5, 2.0), 2 * math.pi * 0.5 * 2 + 2 * math.pi * 0.25),
    (
        "cylinder-scaled",
        lambda: _placed(Cylinder, 0.5, 2.0, scale=3, rotate=(45, 0, 0)),
        9 * 2.5 * math.pi,
    ),
    ("cone", lambda: Cone(1.0, 2.0), _cone_area(1.0, 2.0)),
    (
        "cone-scaled",
        lambda: _placed(Cone, 1.0, 2.0, scale=0.5, translate=(3, 3, 3)),
        _cone_area(0.5, 1.0),
    ),
    ("mesh-cube", unit_cube_mesh, 6.0),
    (
        "mesh-box",
        lambda: _placed(QuadMesh, CUBE_V, CUBE_F, scale=(2, 3, 4), rotate=(0, 30, 0)),
        52.0,
    ),
    ("pyramid", pyramid, 4 + 4 * S2),
]


@pytest.mark.parametrize("case", AREAS, ids=[c[0] for c in AREAS])
def test_area_closed_form(x64, case):
    _, make, exact = case
    assert float(make().area()) == pytest.approx(exact, rel=1e-12)


@pytest.mark.parametrize(
    "cls, args, hi",
    [(Sphere, (1.0,), (1, 2, 1)), (Cylinder, (1.0, 2.0), (1, 4, 1)), (Cone, (1.0, 2.0), (1, 4, 1))],
)
def test_nonuniform_scale_rejected_for_quadrics(x64, cls, args, hi):
    s = _placed(cls, *args, scale=(1, 2, 1))
    with pytest.raises(ValueError, match="needs a uniform scale"):
        s.area()
    with pytest.raises(ValueError, match="needs a uniform scale"):
        s.sample(np.full((4, 3), 0.5))
    # intersection, bounds and tessellation still work
    t, _ = _hit(s, (0, 0.5, -5), (0, 0, 1))
    assert np.isfinite(t)
    np.testing.assert_allclose(s.bounds()[1], hi, atol=1e-12)
    assert len(s.tessellate(8)[1]) > 0


# --- sampling: uniform by area -------------------------------------------------------------------
N_SAMPLES = 40_000


def _uniforms(n, seed):
    return np.random.default_rng(seed).random((n, 3))


def _sample_obj(shape, seed, n=N_SAMPLES):
    """Samples mapped back to object space (float64) with world normals."""
    p, nrm = shape.sample(_uniforms(n, seed))
    p, nrm = np.asarray(p, np.float64), np.asarray(nrm, np.float64)
    inv = np.asarray(shape.to_object, np.float64)
    return p @ inv[:3, :3].T + inv[:3, 3], p, nrm


def _chisq(cells, areas):
    counts = np.bincount(cells, minlength=len(areas))
    assert counts.sum() == len(cells)
    expected = np.asarray(areas) / np.sum(areas) * len(cells)
    return stats.chisquare(counts, expected).pvalue


def test_sphere_sampler_archimedes_bands():
    s = _placed(Sphere, 2.0, translate=(1, -2, 3), rotate=(20, 40, 60), scale=1.5)
    q, _, _ = _sample_obj(s, 1)
    r = 2.0
    band = np.clip(((q[:, 1] + r) / (2 * r) * 5).astype(int), 0, 4)  # equal heights, y axis
    sector = ((np.arctan2(q[:, 2], q[:, 0]) + np.pi) / (np.pi / 2)).astype(int) % 4
    assert _chisq(band * 4 + sector, np.ones(20)) > 1e-3


def test_cylinder_sampler_caps_vs_side():
    r, h = 0.8, 2.5
    c = _placed(Cylinder, r, h, translate=(0, 1, 0), rotate=(0, 90, 30), scale=0.7)
    q, _, _ = _sample_obj(c, 2)
    tol = 1e-4
    bottom, top = np.abs(q[:, 1]) < tol, np.abs(q[:, 1] - h) < tol
    side = ~(bottom | top)
    np.testing.assert_allclose(np.hypot(q[side, 0], q[side, 2]), r, rtol=1e-5)
    inner = np.hypot(q[:, 0], q[:, 2]) < r / S2  # the inner disc is half a cap's area
    band = np.clip((q[:, 1] / h * 4).astype(int), 0, 3)
    cell = np.where(bottom, inner.astype(int), np.where(top, 2 + inner, 4 + band))
    cap, side_band = math.pi * r * r / 2, 2 * math.pi * r * h / 4
    assert _chisq(cell, [cap] * 4 + [side_band] * 4) > 1e-3


def test_cone_sampler_lateral_bands():
    r, h = 1.0, 2.0
    c = _placed(Cone, r, h, rotate=(0, 0, 45), translate=(2, 0, 0))
    q, _, _ = _sample_obj(c, 3)
    slant = math.hypot(r, h)
    base = np.abs(q[:, 1]) < 1e-5
    # lateral area above height y: pi r L ((h - y) / h)^2; bands of equal height
    edges = np.linspace(0, h, 5)
    frac = ((h - edges) / h) ** 2
    band_areas = math.pi * r * slant * (frac[:-1] - frac[1:])
    band = np.clip(np.searchsorted(edges, q[:, 1], side="right") - 1, 0, 3)
    inner = np.hypot(q[:, 0], q[:, 2]) < r / S2
    cell = np.where(base, 4 + inner.astype(int), band)
    cap = math.pi * r * r / 2
    assert _chisq(cell, list(band_areas) + [cap, cap]) > 1e-3


def test_box_sampler_faces_under_nonuniform_scale():
    b = _placed(Cube, (1, 2, 3), scale=(2, 1, 0.5), rotate=(10, 0, 0))  # a (2, 2, 1.5) box
    q, _, _ = _sample_obj(b, 4)
    h = np.array([0.5, 1, 1.5])
    axis = np.argmax(np.abs(q) / h, axis=1)
    sign = np.sign(q[np.arange(len(q)), axis]) > 0
    cell = 2 * axis + sign
    face = {0: 2 * 1.5, 1: 2 * 1.5, 2: 2 * 2}  # world face areas: normal x, y, z
    assert _chisq(cell, [face[i // 2] for i in range(6)]) > 1e-3


def test_mesh_sampler_by_triangle_area():
    m = _placed(QuadMesh, PYR_V, PYR_F, translate=(0, 0, 5), rotate=(30, 0, 0), scale=1.3)
    q, _, _ = _sample_obj(m, 5)
    base = np.abs(q[:, 1]) < 1e-5
    # side faces: which of the four directions (-z, +x, +z, -x) the point lies towards
    side = np.where(
        np.abs(q[:, 2]) >= np.abs(q[:, 0]), np.where(q[:, 2] < 0, 1, 3), np.where(q[:, 0] > 0, 2, 4)
    )
    cell = np.where(base, 0, side)
    assert _chisq(cell, [4.0] + [S2] * 4) > 1e-3
    # within the base quad, the two triangles (split along a diagonal) are equally likely
    qb = q[base]
    assert _chisq((qb[:, 0] > qb[:, 2]).astype(int), [1, 1]) > 1e-3
    # and uniform within each triangle: the four quadrants of the base have equal areas
    assert _chisq(2 * (qb[:, 0] > 0) + (qb[:, 2] > 0), [1, 1, 1, 1]) > 1e-3


def test_sampler_detects_a_wrong_distribution():
    # The chi-square machinery must reject a non-uniform sampler (here: uniform in height on
    # a cone's lateral surface, which over-weights the tip).
    h, n = 2.0, N_SAMPLES
    y = np.random.default_rng(0).random(n) * h
    edges = np.linspace(0, h, 5)
    frac = ((h - edges) / h) ** 2
    band = np.clip(np.searchsorted(edges, y, side="right") - 1, 0, 3)
    assert _chisq(band, frac[:-1] - frac[1:]) < 1e-6


def _cone_centroid_y(r, h):
    slant = math.hypot(r, h)
    return (math.pi * r * slant * h / 3) / (math.pi * r * slant + math.pi * r * r)


CENTROIDS = [
    # (id, shape, object-space surface centroid)
    ("sphere", lambda: Sphere(1.3), (0, 0, 0)),
    ("box", lambda: Cube((1, 2, 3)), (0, 0, 0)),
    ("cylinder", lambda: Cylinder(0.5, 3.0), (0, 1.5, 0)),
    ("cone", lambda: Cone(1.0, 2.0), (0, _cone_centroid_y(1.0, 2.0), 0)),
    ("cone-flat", lambda: Cone(2.0, 0.5), (0, _cone_centroid_y(2.0, 0.5), 0)),
    ("pyramid", pyramid, (0, S2 / (3 * (1 + S2)), 0)),
]


@pytest.mark.parametrize("case", CENTROIDS, ids=[c[0] for c in CENTROIDS])
def test_sample_mean_of_linear_function(x64, case):
    """E[a . p + b] over the surface = a . centroid + b (centroid moved by the placement)."""
    _, make, centroid = case
    w, o = placement(translate=(1, -2, 0.5), rotate=(15, -30, 70), scale=1.7)
    shape = make()
    shape = type(shape)(*_params(shape), to_world=w, to_object=o)
    a, b = np.array([0.3, -1.1, 0.7]), 2.0
    _, p, _ = _sample_obj(shape, 11)
    f = p @ a + b
    exact = a @ (w[:3, :3] @ np.asarray(centroid) + w[:3, 3]) + b
    assert abs(f.mean() - exact) < 5 * f.std() / math.sqrt(len(f))


def _params(shape):
    if isinstance(shape, Sphere):
        return (shape.radius,)
    if isinstance(shape, Cube):
        return (shape.size,)
    if isinstance(shape, Cylinder | Cone):
        return (shape.radius, shape.height)
    return (shape.vertices, np.asarray(shape.triangles))


SURFACES = [
    ("sphere", lambda w, o: Sphere(1.3, w, o)),
    ("box", lambda w, o: Cube((1, 2, 3), w, o)),
    ("cylinder", lambda w, o: Cylinder(0.5, 3.0, w, o)),
    ("cone", lambda w, o: Cone(1.0, 2.0, w, o)),
    ("pyramid", lambda w, o: QuadMesh(PYR_V, PYR_F, w, o)),
    ("mesh-cube", lambda w, o: QuadMesh(CUBE_V, CUBE_F, w, o)),
]


@pytest.mark.parametrize("case", SURFACES, ids=[c[0] for c in SURFACES])
def test_samples_lie_on_surface_and_normals_agree_with_intersect(x64, case):
    _, make = case
    w, o = placement(translate=(0.5, 1, -2), rotate=(25, 50, -10), scale=1.4)
    shape = make(w, o)
    q, p, n = _sample_obj(shape, 21)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    # A ray from outside along -n towards each point first meets the (convex) surface there.
    delta = 0.3
    t, n_hit = shape.intersect(p + delta * n, -n)
    np.testing.assert_allclose(t, delta, atol=1e-9)
    np.testing.assert_allclose(n_hit, n, atol=1e-9)
    # ... and from inside (towards an interior point of the convex body) a ray through the
    # point exits there, with the same outward normal.
    c = p.mean(axis=0)
    t, n_hit = shape.intersect(p - 0.01 * (p - c), p - c)
    np.testing.assert_allclose(t, 0.01, atol=1e-9)
    np.testing.assert_allclose(n_hit, n, atol=1e-9)


def test_sampled_points_satisfy_implicit_equations(x64):
    q, _, _ = _sample_obj(Sphere(1.3), 31)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.3, rtol=1e-12)
    q, _, n = _sample_obj(Cone(1.0, 2.0), 32)
    base = np.abs(q[:, 1]) < 1e-12
    rho = np.hypot(q[:, 0], q[:, 2])
    np.testing.assert_allclose(rho[~base], 1.0 * (1 - q[~base, 1] / 2.0), atol=1e-12)
    assert np.all(rho[base] <= 1.0 + 1e-12)
    np.testing.assert_allclose(n[base], np.tile([0, -1, 0], (base.sum(), 1)), atol=1e-12)
    # lateral normal (H cos phi, R, H sin phi) / L
    phi = np.arctan2(q[~base, 2], q[~base, 0])
    expect = np.stack([2 * np.cos(phi), np.ones_like(phi), 2 * np.sin(phi)], -1) / S5
    np.testing.assert_allclose(n[~base], expect, atol=1e-9)
    q, _, _ = _sample_obj(Cube((1, 2, 3)), 33)
    np.testing.assert_allclose(np.max(np.abs(q) / [0.5, 1, 1.5], axis=1), 1.0, rtol=1e-12)


def test_sample_float32_default_and_shapes():
    s = Cylinder(1.0, 2.0)
    p, n = s.sample(np.full((2, 5, 3), 0.3, np.float32))
    assert p.shape == (2, 5, 3) and n.shape == (2, 5, 3)
    assert p.dtype == jnp.float32 and s.radius.dtype == jnp.float32


# --- bounds and tessellation ---------------------------------------------------------------------
def _signed_volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0


def _tri_area(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()


BOUNDS = [
    # (id, shape, exact lo, exact hi, exact area, exact volume)
    (
        "sphere",
        lambda: _placed(Sphere, 1.0, translate=(1, 2, 3), scale=2, rotate=(10, 20, 30)),
        (-1, 0, 1),
        (3, 4, 5),
        16 * math.pi,
        32 / 3 * math.pi,
    ),
    (
        "box-diamond",
        lambda: _placed(Cube, 2.0, rotate=(0, 0, 45)),
        (-S2, -S2, -1),
        (S2, S2, 1),
        24.0,
        8.0,
    ),
    (
        "cylinder-along-x",
        lambda: _placed(Cylinder, 1.0, 2.0, translate=(1, 0, 0), rotate=(0, 0, -90), scale=2),
        (1, -2, -2),
        (5, 2, 2),
        16 * math.pi + 8 * math.pi,
        16 * math.pi,
    ),
    (
        "cone-down",
        lambda: _placed(Cone, 1.0, 2.0, rotate=(180, 0, 0), translate=(0, 0, 1)),
        (-1, -2, 0),
        (1, 0, 2),
        _cone_area(1.0, 2.0),
        2 * math.pi / 3,
    ),
    (
        "mesh-box",
        lambda: _placed(QuadMesh, CUBE_V, CUBE_F, translate=(5, 0, 0), scale=(2, 3, 4)),
        (5, 0, 0),
        (7, 3, 4),
        52.0,
        24.0,
    ),
]


@pytest.mark.parametrize("case", BOUNDS, ids=[c[0] for c in BOUNDS])
def test_bounds_and_tessellation(x64, case):
    _, make, lo, hi, area, volume = case
    shape = make()
    b_lo, b_hi = shape.bounds()
    np.testing.assert_allclose(b_lo, lo, atol=1e-12)
    np.testing.assert_allclose(b_hi, hi, atol=1e-12)
    v, f = shape.tessellate(resolution=128)
    assert v.dtype == np.float64 and f.shape[1] == 3 and np.issubdtype(f.dtype, np.integer)
    # Inscribed polygons: relative errors O((pi / n)^2); exact for the flat shapes.
    tol = 2e-3
    assert _tri_area(v, f) == pytest.approx(area, rel=tol)
    assert _tri_area(v, f) <= area * (1 + 1e-12)
    assert _signed_volume(v, f) == pytest.approx(volume, rel=tol)  # > 0: wound outward
    # vertices lie on the surface: inside the exact box, and reaching it up to the sagitta
    assert np.all(v.min(0) >= np.asarray(lo) - 1e-12) and np.all(v.max(0) <= np.asarray(hi) + 1e-12)
    np.testing.assert_allclose(v.min(0), lo, atol=2e-3)
    np.testing.assert_allclose(v.max(0), hi, atol=2e-3)
    # every triangle faces away from the (convex) body's centre
    centre = v.mean(0)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    assert np.all(np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3 - centre) > 0)


@pytest.mark.parametrize(
    "cls, args", [(Sphere, (1.0,)), (Cylinder, (1.0, 2.0)), (Cone, (1.0, 2.0))]
)
def test_tessellation_is_closed_and_converges(cls, args):
    v, f = cls(*args).tessellate(16)
    # Watertight: every directed edge appears once and its reverse once (positions, as caps
    # have their own rim vertices).
    pos = {i: tuple(np.round(x, 9)) for i, x in enumerate(v)}
    edges = [
        (pos[a], pos[b])
        for tri in f
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))
    ]
    assert len(set(edges)) == len(edges)
    assert all((b, a) in set(edges) for a, b in edges)
    exact = float(cls(*args).area())
    e1 = exact - _tri_area(*cls(*args).tessellate(16))
    e2 = exact - _tri_area(*cls(*args).tessellate(32))
    assert 0 < e2 < e1 / 3  # second-order convergence from below


# --- OBJ -------------------------------------------------------------------------------------------
OBJ_TEXT = """\
# a unit square pyramid, quad base and triangle sides
o pyramid
v -1 0 -1
v 1 0 -1
v 1.0 0.0 1.0
v -1 0 1 1.0
v 0 1 0
vt 0 0
vn 0 1 0
usemtl skin
f 1/1/1 2/1/1 3/1/1 4/1/1
f 1//1 5//1 2//1
f 2/1 5/1 3/1
f -3 -1 -2
s off
f 4 5 1   # trailing comment
"""


def test_load_obj_mixed_faces(tmp_path):
    path = tmp_path / "pyr.obj"
    path.write_text(OBJ_TEXT)
    v, faces = load_obj(path)
    np.testing.assert_array_equal(v, PYR_V)
    assert [list(f) for f in faces] == [[0, 1, 2, 3], [0, 4, 1], [1, 4, 2], [2, 4, 3], [3, 4, 0]]
    m = QuadMesh(v, faces)
    assert m.triangles.shape == (6, 3)
    np.testing.assert_array_equal(np.asarray(m.triangles[:2]), [[0, 1, 2], [0, 2, 3]])
    assert float(m.area()) == pytest.approx(4 + 4 * S2, rel=1e-6)
    m2 = make_shape("QuadMesh", {"path": str(path)}, translate=(0, 1, 0))
    assert m2.bounds()[0][1] == pytest.approx(1.0)


@pytest.mark.parametrize(
    "bad, line, match",
    [
        ("v 1 2\n", 3, "vertex"),
        ("v 1 2 z\n", 3, "vertex"),
        ("f 1 2\n", 3, "at least 3"),
        ("f 1 2 x\n", 3, "bad face"),
        ("f 1 2 9\n", 3, "out of range"),
        ("f 1 2 -7\n", 3, "out of range"),
        ("f 0 1 2\n", 3, "0"),
        ("f 1/2/3/4 2 3\n", 3, "bad face"),
    ],
)
def test_load_obj_malformed_reports_line(tmp_path, bad, line, match):
    path = tmp_path / "bad.obj"
    path.write_text("v 0 0 0\n# comment\n" + bad + "v 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=match) as e:
        load_obj(path)
    assert f"{path}:{line}:" in str(e.value)


def test_load_obj_forward_reference_and_missing_file(tmp_path):
    path = tmp_path / "fwd.obj"
    path.write_text("f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n")
    v, faces = load_obj(path)
    assert v.shape == (3, 3) and faces == [[0, 1, 2]]
    missing = tmp_path / "nope.obj"
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        load_obj(missing)


# --- construction and validation ------------------------------------------------------------------
def test_make_shape_and_validation(x64):
    s = make_shape("sphere", {"radius": 1.0}, translate=(0, 0, 5), scale=2)
    t, _ = _hit(s, (0, 0, 0), (0, 0, 1))
    assert t == pytest.approx(3.0)
    c = make_shape("Cube", {"size": [1, 2, 3]})
    np.testing.assert_allclose(c.bounds()[1], [0.5, 1, 1.5])
    assert isinstance(make_shape("cylinder", {"radius": 1, "height": 2}), Cylinder)
    assert isinstance(make_shape("cone", {"radius": 1, "height": 2}), Cone)
    m = make_shape("quadmesh", {"vertices": CUBE_V, "faces": CUBE_F}, rotate=(0, 90, 0))
    assert float(m.area()) == pytest.approx(6.0)
    with pytest.raises(ValueError, match="unknown shape kind"):
        make_shape("torus", {"radius": 1})
    with pytest.raises(ValueError, match="missing"):
        make_shape("cylinder", {"radius": 1})
    with pytest.raises(ValueError, match="unexpected"):
        make_shape("sphere", {"radius": 1, "height": 3})
    with pytest.raises(ValueError, match="radius"):
        Sphere(-1.0)
    with pytest.raises(ValueError, match="size"):
        Cube((1, 2))
    with pytest.raises(ValueError, match="out of range"):
        QuadMesh(CUBE_V, [[0, 1, 8]])
    with pytest.raises(ValueError, match="inverse"):
        Sphere(1.0, to_world=np.diag([2.0, 2, 2, 1]), to_object=np.eye(4))
    # to_object alone is enough; to_world is its inverse
    s = Sphere(1.0, to_object=np.diag([0.5, 0.5, 0.5, 1]))
    assert float(s.area()) == pytest.approx(16 * math.pi)


# --- jit, vmap, scenes -------------------------------------------------------------------------------
def test_jit_vmap_and_traced_shapes():
    cases = [c for c in HITS if c[0] in ("box-oblique", "cone-side", "pyramid-side")]

    @eqx.filter_jit
    def run(shape, o, d, u):
        return shape.intersect(o, d), shape.sample(u), shape.area()

    u = jnp.asarray(np.random.default_rng(3).random((8, 3)), jnp.float32)
    for _, make, o, d, t_exp, n_exp in cases:
        s = make()
        o8, d8 = (
            jnp.tile(jnp.asarray([o], jnp.float32), (8, 1)),
            jnp.tile(jnp.asarray([d], jnp.float32), (8, 1)),
        )
        (t, n), (p, pn), a = run(s, o8, d8, u)
        assert t.dtype == jnp.float32 and p.shape == (8, 3)
        np.testing.assert_allclose(t, t_exp, rtol=1e-5)
        np.testing.assert_allclose(n, np.broadcast_to(n_exp, (8, 3)), atol=1e-5)
        np.testing.assert_allclose(a, s.area(), rtol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(pn, axis=1), 1.0, rtol=1e-5)
    # vmap over single rays of shape (3,)
    s = Sphere(2.0)
    o = jnp.array([[0.0, 0, -5], [1, 0, -5], [0, 2.5, -5]])
    tv, nv = jax.vmap(s.intersect)(o, jnp.array([[0.0, 0, 1]] * 3))
    np.testing.assert_allclose(tv, [3.0, 5 - S3, np.inf], rtol=1e-6)
    np.testing.assert_allclose(nv[1], [0.5, 0, -S3 / 2], atol=1e-6)
    # a batch of shapes: vmap over a stacked pytree of spheres
    radii = jnp.array([1.0, 2.0, 3.0])
    t = jax.vmap(
        lambda r: Sphere(r).intersect(jnp.array([[0.0, 0, -5]]), jnp.array([[0.0, 0, 1]]))[0]
    )(radii)
    np.testing.assert_allclose(t[:, 0], [4.0, 3.0, 2.0], rtol=1e-6)


def test_intersect_all_nearest_and_index():
    scene = [
        _placed(Sphere, 1.0, translate=(0, 0, 5)),
        Cube(2.0),
        _placed(Cylinder, 0.5, 1.0, translate=(0, 0, -5), rotate=(90, 0, 0)),
    ]
    o = jnp.array([[0.0, 0, -10], [0, 0, 10], [0, 5, 0], [0, 0, 0]])
    d = jnp.array([[0.0, 0, 1], [0, 0, -1], [0, 1, 0], [1, 0, 0]])
    t, n, idx = jax.jit(intersect_all)(scene, o, d)
    # ray 0: cylinder (axis +z after Rx(90), from z = -5 to -4): bottom cap at z = -5, t = 5
    # ray 1: sphere front at z = 6, t = 4;  ray 2: miss;  ray 3: cube from inside, t = 1
    np.testing.assert_allclose(t, [5.0, 4.0, np.inf, 1.0], rtol=1e-6)
    np.testing.assert_array_equal(idx, [2, 0, -1, 1])
    np.testing.assert_allclose(n, [[0, 0, -1], [0, 0, 1], [0, 0, 0], [1, 0, 0]], atol=1e-6)
    assert idx.dtype == jnp.int32
    t, n, idx = intersect_all([], o, d)
    assert np.all(np.isinf(t)) and np.all(idx == -1)


def test_float64_under_x64(x64):
    s = Sphere(2.0)
    t, n = s.intersect(jnp.array([[0.0, 0, -5]]), jnp.array([[0.0, 0, 1]]))
    assert t.dtype == jnp.float64 and s.radius.dtype == jnp.float64
    # Far origin: the closest-point formulation keeps the hit accurate.
    t, _ = Sphere(1.0).intersect(jnp.array([[0.3, 0, -1e6]]), jnp.array([[0.0, 0, 1]]))
    assert float(t[0]) == pytest.approx(1e6 - math.sqrt(1 - 0.09), abs=1e-8)


def test_far_origin_float32():
    t, n = Sphere(1.0).intersect(jnp.array([[0.6, 0, -1e4]]), jnp.array([[0.0, 0, 1]]))
    assert float(t[0]) == pytest.approx(1e4 - 0.8, abs=2e-3)
    np.testing.assert_allclose(n[0], [0.6, 0, -0.8], atol=1e-3)


# --- large batches -------------------------------------------------------------------------
def test_large_ray_batches_match_closed_forms():
    """A render casts ~10^5 rays per call. jaxlib 0.10.2 on the CPU miscompiled the mesh
    test for batches over 2^15 elements (rays past the 16,384th got another ray's `t`), so
    here a 40,000-ray float32 batch (shadow rays up and down from a floor plane, through a
    box) is checked against the closed-form plane and box answers, under `jit` as in `trace`."""
    rng = np.random.default_rng(3)
    n = 40_000
    o = np.c_[rng.uniform(-60, 60, n), rng.choice([1e-3, -1e-3, 5.0], n), rng.uniform(-60, 60, n)]
    d = np.c_[rng.uniform(-0.3, 0.3, n), rng.choice([1.0, -1.0], n), rng.uniform(-0.3, 0.3, n)]
    floor = QuadMesh(
        [[-200.0, 0.0, -200.0], [-200.0, 0.0, 200.0], [200.0, 0.0, 200.0], [200.0, 0.0, -200.0]],
        [[0, 1, 2, 3]],
    )
    box = _placed(Cube, 20.0, translate=(0.0, 10.0, 0.0))
    t, _, sid = jax.jit(lambda o, d: intersect_all([box, floor], o, d, 1e-4, jnp.inf))(
        o.astype(np.float32), d.astype(np.float32)
    )
    t, sid = np.asarray(t, np.float64), np.asarray(sid)
    # closed forms (float64): the plane y = 0 and the slab box [-10, 10] x [0, 20] x [-10, 10]
    t_plane = np.where(-o[:, 1] / d[:, 1] > 1e-4, -o[:, 1] / d[:, 1], np.inf)
    lo, hi = np.array([-10.0, 0.0, -10.0]), np.array([10.0, 20.0, 10.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t0 = np.max(np.minimum(ta, tb), axis=1)
    t1 = np.min(np.maximum(ta, tb), axis=1)
    t_box = np.where((t1 >= t0) & (t1 > 1e-4), np.where(t0 > 1e-4, t0, t1), np.inf)
    want = np.minimum(t_plane, t_box)
    want_sid = np.where(np.isinf(want), -1, np.where(t_box <= t_plane, 0, 1))
    # rays grazing the box's edges may go either way within float32: skip the few within 1e-3
    edge = np.abs(t1 - t0) < 1e-3
    ok = np.isclose(t, want, rtol=1e-4, atol=1e-3) | (np.isinf(t) & np.isinf(want))
    wrong = np.flatnonzero(~ok & ~edge)
    assert len(wrong) == 0, f"{len(wrong)} of {n} rays wrong, first {wrong[:5]}"
    with np.errstate(invalid="ignore"):  # inf - inf where both miss
        tie = np.abs(t_box - t_plane) < 1e-3  # the box's bottom face lies on the floor
    assert np.all((sid == want_sid) | edge | tie)
    assert np.isfinite(t).sum() > n // 4 and np.isinf(t).sum() > n // 4  # both cases exercised
