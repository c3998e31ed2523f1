"""Jensen's measurement setup: the collimated beam light, the orthographic camera, and the
measurement step (`sssjax measure`) on images the renderer made.

Expected values are closed forms: a beam of power `P` and radius `R` hitting a plane at
angle `theta` lights an ellipse of area `pi R^2 / cos(theta)` with irradiance
`P cos(theta) / (pi R^2)`, so a Lambertian floor shows `albedo / pi` times that inside and
nothing outside, and the power it receives is `P`. The beam's share of the irradiance cloud
carries `P F_t(theta)` into a translucent slab. Units: mm, W.
"""

import dataclasses
import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sssjax
from sssjax import dipole
from sssjax.camera import camera_rays, project
from sssjax.cli import main
from sssjax.imageio import write_image
from sssjax.measure import find_center, fit_profile, image_to_reflectance, radial_profile
from sssjax.render import Renderer

SLAB = Path(__file__).parent.parent / "scenes" / "measurement_slab.toml"


def beam_dir(theta_deg):
    t = math.radians(theta_deg)
    return [math.sin(t), -math.cos(t), 0.0]


def floor_scene(theta_deg, radius, power, albedo=0.5, n=64, view=20.0):
    d = np.array(beam_dir(theta_deg))
    pos = (-60.0 / math.cos(math.radians(theta_deg))) * d  # hits the floor at the origin
    return sssjax.load_scene(
        {
            "camera": {
                "projection": "orthographic",
                "origin": [0.0, 100.0, 0.0],
                "target": [0.0, 0.0, 0.0],
                "up": [0.0, 0.0, -1.0],
                "view_width": view,
                "width": n,
                "height": n,
            },
            "render": {"spp": 4, "light_samples": 1, "max_depth": 0},
            "sss": {"enabled": False},
            "lights": [
                {
                    "type": "beam",
                    "position": pos.tolist(),
                    "direction": d.tolist(),
                    "radius": radius,
                    "power": power,
                }
            ],
            "materials": {"floor": {"type": "diffuse", "albedo": albedo}},
            "shapes": [
                {
                    "type": "quadmesh",
                    "material": "floor",
                    "vertices": [[-500, 0, -500], [-500, 0, 500], [500, 0, 500], [500, 0, -500]],
                    "faces": [[0, 1, 2, 3]],
                }
            ],
        }
    )


def test_orthographic_rays_are_parallel_and_project_inverts_them():
    sc = floor_scene(0.0, 1.0, 1.0)
    cam = dataclasses.replace(sc.camera, width=40, height=30)
    pix = jnp.arange(cam.width * cam.height)
    jit = jax.random.uniform(jax.random.key(0), (pix.shape[0], 3, 2))
    o, d = camera_rays(cam, pix, jit)
    np.testing.assert_allclose(np.asarray(d), np.broadcast_to([0.0, -1.0, 0.0], d.shape), atol=1e-6)
    xy = np.asarray(project(cam, (o + 37.0 * d).reshape(-1, 3))).reshape(-1, 3, 2)
    want = np.stack([pix % cam.width, pix // cam.width], -1)[:, None, :] + np.asarray(jit)
    np.testing.assert_allclose(xy, want, atol=1e-3)
    # square pixels of view_width / width mm: the image spans view_width x view_width * h / w
    span = np.ptp(np.asarray(o)[..., [0, 2]].reshape(-1, 2), axis=0)
    np.testing.assert_allclose(span, [20.0, 20.0 * 30 / 40], rtol=0.02)


@pytest.mark.parametrize("theta", [0.0, 40.0])
def test_beam_on_lambertian_floor(theta):
    R, P, albedo, n, view = 3.0, 2.0, 0.5, 64, 20.0
    sc = floor_scene(theta, R, P, albedo, n, view)
    img = np.asarray(sssjax.render(sc, 0))[..., 0]
    px = view / n
    cos = math.cos(math.radians(theta))
    L_in = albedo / math.pi * P * cos / (math.pi * R**2)
    # pixel centres in world x (right) and z: image x -> world x, image y -> world z
    c = (np.arange(n) + 0.5) * px - view / 2
    X, Z = np.meshgrid(c, c)  # rows: z, cols: x
    rho = (X * cos / R) ** 2 + (Z / R) ** 2  # the footprint ellipse (semi-axes R/cos, R)
    inside = rho < (1 - 1.5 * px / R) ** 2  # pixels entirely inside the footprint
    outside = rho > (1 + 1.5 * px / (R * cos)) ** 2
    assert inside.sum() > 20 and outside.sum() > 1000
    np.testing.assert_allclose(img[inside], L_in, rtol=1e-4)
    assert np.all(img[outside] == 0.0)
    # every watt lands on the floor: sum of pi L / albedo over pixel areas is P (AA edges
    # are averages over the pixel, so the sum is exact up to the jitter's noise)
    total = np.sum(img * math.pi / albedo) * px * px
    assert abs(total / P - 1) < 0.01, total


def test_beam_blocked_by_occluder():
    """A diffuse plate across half the beam shadows that half of the footprint."""
    sc = floor_scene(0.0, 3.0, 1.0)
    src = dict(sc.source)
    src["materials"] = {**src["materials"], "plate": {"type": "diffuse", "albedo": 0.0}}
    plate = {
        "type": "quadmesh",
        "material": "plate",
        "vertices": [[0, 30, -50], [0, 30, 50], [50, 30, 50], [50, 30, -50]],
        "faces": [[0, 1, 2, 3]],
    }
    src["shapes"] = [*src["shapes"], plate]
    src["camera"] = {**src["camera"], "origin": [0.0, 20.0, 0.0]}  # below the plate
    img = np.asarray(sssjax.render(sssjax.load_scene(src), 0))[..., 0]
    n = img.shape[1]
    left, right = img[:, : n // 2 - 1], img[:, n // 2 + 1 :]
    assert left.max() > 0 and right.max() == 0.0


@pytest.mark.parametrize("theta", [0.0, 40.0])
def test_beam_cloud_carries_transmitted_power(theta):
    sc = sssjax.load_scene(SLAB)
    d = beam_dir(theta)
    lights = list(sc.source["lights"])
    lights[0] = {**lights[0], "direction": d, "position": [0.0, 50.0, 0.0]}
    sc = sssjax.load_scene({**sc.source, "lights": lights})
    cloud = Renderer(sc).image_state(jax.random.key(1))
    eta = float(sc.media()["sample"].eta)
    Ft = float(dipole.fresnel_transmittance(math.cos(math.radians(theta)), eta))
    flux = np.asarray(cloud.beam_flux)
    np.testing.assert_allclose(flux.sum(axis=(0, 1)), Ft * 1.0, rtol=1e-4)
    pts = np.asarray(cloud.beam_points)[0]
    np.testing.assert_allclose(pts[:, 1], 0.0, atol=1e-4)  # on the top face
    # within the footprint ellipse around where the axis meets the surface
    hit_x = 50.0 * math.tan(math.radians(theta))
    cos = math.cos(math.radians(theta))
    rho = ((pts[:, 0] - hit_x) * cos / 0.1) ** 2 + (pts[:, 2] / 0.1) ** 2
    assert rho.max() <= 1.0 + 1e-3


def render_slab(material: str, n: int = 128):
    sc = sssjax.load_scene(SLAB)
    mats = {"sample": {"type": "translucent", "preset": material}}
    sc = sssjax.load_scene({**sc.source, "materials": mats}).with_settings(width=n, height=n)
    return sc, np.asarray(sssjax.render(sc, 0))


@pytest.mark.slow
@pytest.mark.parametrize("material", ["marble", "skimmilk"])
def test_measurement_step_recovers_rendered_beam_target(material):
    """The issue's floor: within 2% of the renderer's coefficients, for every channel."""
    sc, img = render_slab(material)
    m = sc.media()["sample"]
    eta = float(m.eta)
    cx, cy = find_center(img)
    assert abs(cx - 64) < 0.5 and abs(cy - 64) < 0.5
    R = image_to_reflectance(img, eta, power=1.0)
    prof = radial_profile(R, (cx, cy), sc.camera.pixel_size_mm)
    fit = fit_profile(prof, eta, orders="multiple", r_min=1.0)
    assert all(fit.converged)
    np.testing.assert_allclose(fit.sigma_a, np.asarray(m.sigma_a), rtol=0.02)
    np.testing.assert_allclose(fit.sigmap_s, np.asarray(m.sigmap_s), rtol=0.02)
    # and with a free intensity scale (an uncalibrated camera): still close, larger errors
    free = fit_profile(prof, eta, orders="multiple", r_min=1.0, free_scale=True)
    np.testing.assert_allclose(free.sigmap_s, np.asarray(m.sigmap_s), rtol=0.05)
    assert np.all(free.sigma_a_stderr > fit.sigma_a_stderr)


@pytest.mark.slow
def test_measure_cli(tmp_path, capsys):
    exr = tmp_path / "img" / "slab.exr"
    assert main(["render", str(SLAB), "-o", str(exr), "--width", "128", "--height", "128"]) == 0
    out = tmp_path / "res"
    assert main(["measure", str(exr), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "sigma_a" in text and "beam power [1.0, 1.0, 1.0] W" in text and "model dipole" in text
    res = json.loads((out / "measure.json").read_text())
    marble = sssjax.preset("marble")
    np.testing.assert_allclose(res["sigma_a"], np.asarray(marble.sigma_a), rtol=0.02)
    np.testing.assert_allclose(res["sigmap_s"], np.asarray(marble.sigmap_s), rtol=0.02)
    assert res["pixel_size_mm"] == pytest.approx(60.0 / 128)
    assert (out / "profile.png").stat().st_size > 10_000
    # never over an existing result without --force
    assert main(["measure", str(exr), "-o", str(out)]) == 2
    assert "exists; use --force" in capsys.readouterr().err


def test_measure_cli_errors(tmp_path, capsys):
    img = np.zeros((32, 32, 3), np.float32)
    black = write_image(tmp_path / "black.exr", img)
    img[16, 16] = 1.0
    img[10:22, 10:22] += 1e-3
    plain = write_image(tmp_path / "plain.exr", img)
    # what sssjax writes with a render of a scene lit by anything but a beam
    lit = {"transport": "volumetric", "profile": "dipole", "pixel_size_mm": 0.1}
    area = write_image(tmp_path / "area.exr", img, metadata=lit)
    cases = [
        (["measure", str(area)], "rendered by sssjax with no beam light: sssjax measure fits"),
        (["measure", str(tmp_path / "nope.exr")], "image not found"),
        (["measure", str(black), "--pixel-size", "0.1"], "all black"),
        (["measure", str(plain)], "no pixel size in the image metadata: give --pixel-size"),
        (["measure", str(plain), "--pixel-size", "-1"], "--pixel-size must be > 0 mm, got -1"),
        (["measure", str(plain), "--pixel-size", "0.1", "--center", "50", "3"], "outside the"),
        (["measure", str(plain), "--pixel-size", "0.1", "--r-min", "5"], "only 0 annuli"),
    ]
    for argv, msg in cases:
        assert main([*argv, "-o", str(tmp_path / "o")]) == 2, argv
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, err
    # beyond the table's eta the tabulated profile is held at its edge: said, not silent
    argv = ["measure", str(plain), "--pixel-size", "0.1", "--eta", "1.8", "--r-min", "5"]
    assert main([*argv, "--model", "tabulated", "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "warning: --eta 1.8 is outside the tabulated profile's range 1.0-1.6" in err, err
    assert main([*argv, "--model", "better_dipole", "-o", str(tmp_path / "o")]) == 2
    assert "outside the tabulated" not in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
