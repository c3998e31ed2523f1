"""The ray tree of one pixel: counts against the settings, chaining, end points on the
geometry (checked with closed-form surface equations written here), and the recorded run's
radiance against the compiled renderer's pixel.

Units: mm. Scene A is a marble cube on a diffuse floor with a mirror, a red sphere that
shadows the floor, an area light and a point light; scene B two parallel mirrors.
"""

import functools
import json

import jax
import numpy as np
import pytest

import sssjax
from sssjax.camera import project
from sssjax.cli import main
from sssjax.raytree import KINDS, RayTree, raytree
from sssjax.render import renderer_for
from sssjax.transport import NO_RECORD

S, NL, NSS, CLOUD, DEPTH = 4, 2, 2, 64, 1  # spp, light_samples (per axis), single, cloud, depth
EPS = 1e-3  # the tracer's ray offset off surfaces (mm)

AREA = dict(corner=[-10.0, 80.0, -10.0], edge_u=[20.0, 0.0, 0.0], edge_v=[0.0, 0.0, 20.0])
POINT = [40.0, 60.0, 40.0]
CUBE_C, CUBE_H = np.array([0.0, 10.0, 0.0]), 10.0
SPHERE_C, SPHERE_R = np.array([24.0, 22.0, 14.0]), 6.0
MIRROR = dict(x=(-45.0, -15.0), y=(0.0, 40.0), z=-30.0)
FLOOR = 60.0  # half size of the floor quad at y = 0


def scene_a(**sss):
    m = MIRROR
    return sssjax.load_scene(
        {
            "camera": {
                "origin": [0, 60, 120],
                "target": [0, 5, 0],
                "fov": 30,
                "width": 16,
                "height": 12,
            },
            "render": {"spp": S, "light_samples": NL, "max_depth": DEPTH, "seed": 3},
            "sss": {"cloud_size": CLOUD, "single_samples": NSS, **sss},
            "lights": [
                {"type": "area", **AREA, "radiance": 5.0},
                {"type": "point", "position": POINT, "intensity": 3000.0},
            ],
            "materials": {
                "marble": {"type": "translucent", "preset": "marble"},
                "floor": {"type": "diffuse", "albedo": 0.6},
                "mirror": {"type": "mirror", "reflectance": 0.9},
                "red": {"type": "diffuse", "albedo": [0.7, 0.1, 0.1]},
            },
            "shapes": [
                {
                    "type": "quadmesh",
                    "material": "floor",
                    "vertices": [
                        [-FLOOR, 0, -FLOOR],
                        [-FLOOR, 0, FLOOR],
                        [FLOOR, 0, FLOOR],
                        [FLOOR, 0, -FLOOR],
                    ],
                    "faces": [[0, 1, 2, 3]],
                },
                {
                    "type": "cube",
                    "material": "marble",
                    "size": [2 * CUBE_H] * 3,
                    "translate": CUBE_C.tolist(),
                },
                {
                    "type": "quadmesh",
                    "material": "mirror",
                    "vertices": [
                        [m["x"][0], m["y"][0], m["z"]],
                        [m["x"][1], m["y"][0], m["z"]],
                        [m["x"][1], m["y"][1], m["z"]],
                        [m["x"][0], m["y"][1], m["z"]],
                    ],
                    "faces": [[0, 1, 2, 3]],
                },
                {
                    "type": "sphere",
                    "material": "red",
                    "radius": SPHERE_R,
                    "translate": SPHERE_C.tolist(),
                },
            ],
        }
    )


def scene_b():
    """Two facing mirrors at x = -20 and x = +20 (1000 mm squares); no floor."""

    def mirror(x, flip):
        v = [[x, -500, -500], [x, 500, -500], [x, 500, 500], [x, -500, 500]]
        return {
            "type": "quadmesh",
            "material": "mirror",
            "vertices": v,
            "faces": [[0, 3, 2, 1] if flip else [0, 1, 2, 3]],
        }

    return sssjax.load_scene(
        {
            "camera": {
                "origin": [0, 0, 0],
                "target": [-20, 0, -30],
                "fov": 10,
                "width": 16,
                "height": 12,
            },
            "render": {"spp": S, "light_samples": NL, "max_depth": 3, "seed": 1},
            "lights": [{"type": "point", "position": [0.0, 0.0, 50.0], "intensity": 100.0}],
            "materials": {"mirror": {"type": "mirror", "reflectance": 0.9}},
            "shapes": [mirror(-20.0, False), mirror(20.0, True)],
        }
    )


def pixel_of(scene, p):
    """The pixel containing the image of world point `p`."""
    xy = np.asarray(project(scene.camera, np.asarray([p], float)))[0]
    return int(xy[0]), int(xy[1])


# --- closed-form surfaces of scene A ---------------------------------------------------------
def on_floor(p, tol=1e-3):
    return (np.abs(p[:, 1]) < tol) & np.all(np.abs(p[:, [0, 2]]) <= FLOOR + tol, axis=1)


def on_cube(p, tol=1e-3):
    return np.abs(np.max(np.abs(p - CUBE_C), axis=1) - CUBE_H) < tol


def on_sphere(p, tol=1e-3):
    return np.abs(np.linalg.norm(p - SPHERE_C, axis=1) - SPHERE_R) < tol


def on_mirror(p, tol=1e-3):
    m = MIRROR
    return (
        (np.abs(p[:, 2] - m["z"]) < tol)
        & (p[:, 0] >= m["x"][0] - tol)
        & (p[:, 0] <= m["x"][1] + tol)
        & (p[:, 1] >= m["y"][0] - tol)
        & (p[:, 1] <= m["y"][1] + tol)
    )


def on_light(p, tol=0.03):
    """On the area light or at the point light (a lit shadow ray stops 1e-4 of its length
    short of the light sample, up to about 0.015 mm here)."""
    c = np.asarray(AREA["corner"])
    area = (np.abs(p[:, 1] - c[1]) < tol) & np.all(
        (p[:, [0, 2]] >= c[[0, 2]] - tol) & (p[:, [0, 2]] <= c[[0, 2]] + 20.0 + tol), axis=1
    )
    return area | (np.linalg.norm(p - np.asarray(POINT), axis=1) < tol)


def diffuse_end(p):
    return on_floor(p) | on_sphere(p)


# --- fixtures ----------------------------------------------------------------------------
@pytest.fixture
def a():
    return _trees_a()


# cached per process rather than in a module fixture: built once whatever order the
# tests run in (a module fixture is torn down and rebuilt when other modules' tests interleave)
@functools.cache
def _trees_a():
    sc = scene_a()
    pix = {
        "cube": pixel_of(sc, [0.0, 10.0, CUBE_H]),  # the middle of the cube's front face
        "mirror": pixel_of(sc, [-30.0, 20.0, MIRROR["z"]]),
        # floor in the point light's shadow of the sphere: light -> sphere centre -> floor
        "shadow": pixel_of(sc, np.asarray(POINT) + 60 / 38 * (SPHERE_C - np.asarray(POINT))),
        "sky": (sc.camera.width - 1, 0),
    }
    image = sssjax.render(sc)
    trees = {k: raytree(sc, p) for k, p in pix.items()}
    image_after = sssjax.render(sc)
    return dict(scene=sc, pix=pix, image=image, image_after=image_after, trees=trees)


def n_shadow_per_vertex(n_area=1, n_point=1):
    return NL * NL * n_area + n_point


def children(tree, i):
    return np.flatnonzero(tree.parent == i)


# --- counts ------------------------------------------------------------------------------
def test_counts_of_a_translucent_pixel_match_the_settings(a):
    t = a["trees"]["cube"]
    c = t.counts()
    assert c["camera"] == S
    # every sample hits the front face: one Fresnel-reflected ray each (which hits the floor
    # or leaves; diffuse ends the chain)
    assert c["reflected"] == S
    assert c["ss_refracted"] == S * NSS
    assert c["ss_light"] == S * NSS * 2  # 2 lights
    assert c["dipole"] == 0  # the cloud strategy casts no per-pixel dipole rays
    # the cloud: each sample gathers from its own 1/spp subset, the whole cloud per pixel
    assert len(t.points) == CLOUD
    assert np.array_equal(np.bincount(t.point_sample, minlength=S), np.full(S, CLOUD // S))
    for s in range(S):  # disjoint subsets
        others = t.points[t.point_sample != s]
        mine = t.points[t.point_sample == s]
        assert np.min(np.linalg.norm(mine[:, None] - others[None], axis=-1)) > 0
    assert np.all(on_cube(t.points)) and np.all(t.point_weight >= 0) and t.point_weight.max() > 0
    # shadow rays: nl^2 per area light + 1 per point light at every diffuse vertex and at the
    # first translucent vertex; one per single-scattering light connection
    chain = np.flatnonzero(t.of_kind("camera", "reflected"))
    shadow = t.of_kind("shadow", "shadow_blocked")
    for i in chain:
        first_t = t.kind[i] == KINDS.index("camera")  # the camera rays end on the cube
        if first_t:
            assert on_cube(t.end[i : i + 1])[0]
        want = n_shadow_per_vertex() if (first_t or diffuse_end(t.end[i : i + 1])[0]) else 0
        assert np.sum(shadow[children(t, i)]) == want
    for i in np.flatnonzero(t.of_kind("ss_light")):
        assert np.sum(shadow[children(t, i)]) == 1
    n_diffuse = int(np.sum(diffuse_end(t.end[chain])))
    assert n_diffuse >= 1  # some reflections reach the floor
    assert c["shadow"] + c["shadow_blocked"] == (S + n_diffuse) * n_shadow_per_vertex() + (
        S * NSS * 2
    )


def test_mirror_pixel_continues_the_chain(a):
    t = a["trees"]["mirror"]
    c = t.counts()
    assert c["camera"] == S and c["reflected"] == S  # mirror -> floor (diffuse ends it)
    cam = t.of_kind("camera")
    assert np.all(on_mirror(t.end[cam]))
    assert (
        np.sum(t.of_kind("shadow", "shadow_blocked")[np.isin(t.parent, np.flatnonzero(cam))]) == 0
    )
    refl = np.flatnonzero(t.of_kind("reflected"))
    assert np.all(on_floor(t.end[refl]))
    assert c["shadow"] + c["shadow_blocked"] == S * n_shadow_per_vertex()
    assert c["ss_refracted"] == c["ss_light"] == 0 and len(t.points) == 0


def test_corridor_of_mirrors_reflects_max_depth_times():
    sc = scene_b()
    t = raytree(sc, (8, 6))
    c = t.counts()
    assert c["camera"] == S and c["reflected"] == S * 3  # max_depth = 3, every bounce alive
    assert c["shadow"] == c["shadow_blocked"] == 0  # mirror vertices cast no shadow rays
    for i in np.flatnonzero(t.of_kind("reflected")):
        p = t.parent[i]
        assert t.depth[i] == t.depth[p] + 1 and t.sample[i] == t.sample[p]
    assert np.allclose(np.abs(t.end[:, 0]), 20.0, atol=1e-3)  # every segment ends on a mirror
    # alternating sides along each chain
    assert np.all(
        np.sign(t.end[t.of_kind("reflected"), 0])
        == -np.sign(t.end[t.parent[t.of_kind("reflected")], 0])
    )
    img = sssjax.render(sc)
    np.testing.assert_allclose(t.radiance, img[6, 8], rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_monte_carlo_dipole_strategy_counts():
    K = 3
    sc = scene_a(strategy="uniform", samples=K, single_scattering=False)
    t = raytree(sc, pixel_of(sc, [0.0, 10.0, CUBE_H]), jax.random.key(11))  # a key, not a seed
    c = t.counts()
    assert c["dipole"] == S * K and len(t.points) == S * K
    assert c["ss_refracted"] == c["ss_light"] == 0
    dip = np.flatnonzero(t.of_kind("dipole"))
    assert np.allclose(t.end[dip], t.points)  # the segments end at the sample points
    assert np.all(on_cube(t.points))
    shadow = t.of_kind("shadow", "shadow_blocked")
    for i in dip:
        assert np.sum(shadow[children(t, i)]) == n_shadow_per_vertex()
        assert t.kind[t.parent[i]] == KINDS.index("camera")
    assert np.all(on_light(t.end[t.of_kind("shadow")]))
    # the samples of one camera sample are stratified over the surface: all distinct
    for s in range(S):
        assert len(np.unique(t.points[t.point_sample == s], axis=0)) == K


# --- structure -----------------------------------------------------------------------------
def test_segments_chain(a):
    offset = {"reflected", "shadow", "shadow_blocked"}  # cast from EPS off the surface
    for t in a["trees"].values():
        has = t.parent >= 0
        assert np.all(t.parent[~has] == -1) and np.all(t.kind[~has] == KINDS.index("camera"))
        assert np.all(t.parent[has] < np.flatnonzero(has))  # parents are recorded first
        gap = np.linalg.norm(t.origin[has] - t.end[t.parent[has]], axis=1)
        kinds = np.array(KINDS)[t.kind[has]]
        off = np.isin(kinds, list(offset))
        assert np.all(gap[~off] < 1e-4), gap[~off].max()
        assert np.all(gap[off] < EPS * 1.001 + 1e-4), gap[off].max()
        # a subsurface path leaves the point where its sample's chain entered the object
        sub = t.of_kind("ss_refracted", "dipole")
        assert np.all(on_cube(t.end[t.parent[sub]]))
        # shadow rays and subsurface segments inherit their parent's sample and depth
        assert np.array_equal(t.sample[has], t.sample[t.parent[has]])
        same = ~t.of_kind("reflected")[has]
        assert np.array_equal(t.depth[has][same], t.depth[t.parent[has]][same])


def test_background_pixel_has_only_camera_rays(a):
    t = a["trees"]["sky"]
    assert t.counts() == {k: (S if k == "camera" else 0) for k in KINDS}
    assert np.all(t.miss) and len(t.points) == 0
    assert np.all(t.radiance == 0)


def test_shadow_rays_end_on_an_occluder_or_a_light(a):
    blocked, lit = [], []
    for t in a["trees"].values():
        blocked.append(t.end[t.of_kind("shadow_blocked")])
        lit.append(t.end[t.of_kind("shadow")])
    blocked, lit = np.concatenate(blocked), np.concatenate(lit)
    on_shape = on_floor(blocked) | on_cube(blocked) | on_sphere(blocked) | on_mirror(blocked)
    assert np.all(on_shape)
    assert np.sum(on_sphere(blocked)) >= 1  # the sphere shadows the floor pixel
    assert np.all(on_light(lit)) and not np.any(on_light(blocked))
    t = a["trees"]["shadow"]
    sph = on_sphere(t.end) & t.of_kind("shadow_blocked")
    assert np.all(t.kind[t.parent[sph]] == KINDS.index("camera")) and sph.any()


# --- the render is the recorded run -------------------------------------------------------
def test_recorded_radiance_is_the_rendered_pixel(a):
    img = a["image"]
    for k, t in a["trees"].items():
        x, y = t.pixel
        np.testing.assert_allclose(t.radiance, img[y, x], rtol=2e-5, atol=1e-7, err_msg=k)
    assert img[a["pix"]["cube"][1], a["pix"]["cube"][0]].max() > 0
    # recording leaves the compiled renderer alone: bit-identical renders before and after
    assert np.array_equal(a["image"], a["image_after"])
    # (the compiled renderer's transport functions record with the no-op recorder)
    assert NO_RECORD.active is False and renderer_for(a["scene"]).transport is not None


# --- JSON and the command line ----------------------------------------------------------
def test_json_round_trip(a, tmp_path):
    t = a["trees"]["cube"]
    back = RayTree.from_json(t.to_json(tmp_path / "t.json"))
    assert back.counts() == t.counts() and back.pixel == t.pixel and back.spp == S
    for f in ("origin", "end", "kind", "depth", "sample", "parent", "miss", "points"):
        np.testing.assert_array_equal(
            getattr(back, f), getattr(t, f).astype(getattr(back, f).dtype)
        )
    d = json.loads((tmp_path / "t.json").read_text())
    assert d["kinds"] == list(KINDS) and d["counts"] == t.counts()


SMALL = """
[camera]
origin = [0.0, 40.0, 80.0]
target = [0.0, 0.0, 0.0]
fov = 40.0
width = 16
height = 12
[render]
spp = 4
light_samples = 2
max_depth = 1
[[lights]]
type = "point"
position = [0.0, 50.0, 0.0]
intensity = [3000.0, 3000.0, 3000.0]
[materials.white]
type = "diffuse"
albedo = 0.7
[[shapes]]
type = "sphere"
material = "white"
radius = 10.0
"""


def test_cli_writes_json_and_picture_and_protects_files(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SMALL)
    js, png = tmp_path / "o" / "t.json", tmp_path / "o" / "t.png"
    args = ["raytree", str(scene), "--pixel", "6", "4", "-o", str(js), "--png", str(png)]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "backdrop" in out and str(js.resolve()) in out
    t = RayTree.from_json(js)
    assert t.pixel == (6, 4) and t.counts()["camera"] == S and t.counts()["shadow"] >= 1
    assert png.stat().st_size > 20_000
    before = js.read_text()
    assert main(args) == 2  # no overwrite without --force
    err = capsys.readouterr().err
    assert "--force" in err and len(err.strip().splitlines()) == 1
    assert js.read_text() == before
    assert main(["raytree", str(scene), "--pixel", "6", "4", "-o", str(scene), "--force"]) == 2
    assert scene.read_text() == SMALL


def test_cli_errors_are_one_line(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SMALL)
    assert main(["raytree", str(scene), "--pixel", "16", "0", "-o", str(tmp_path / "a.json")]) == 2
    err = capsys.readouterr().err
    assert "outside the 16x12 image" in err and len(err.strip().splitlines()) == 1
    assert main(["raytree", str(tmp_path / "nope.toml"), "--pixel", "0", "0"]) == 2
    err = capsys.readouterr().err
    assert "nope.toml" in err and len(err.strip().splitlines()) == 1
