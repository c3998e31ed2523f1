"""Subsurface scattering in the renderer: closed forms, the dense gather, finite differences."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_differences, slab_scene

import sssjax
from sssjax import Medium, dipole, preset, profiles
from sssjax.camera import project
from sssjax.render import Renderer, as_key
from sssjax.shade import shade_sss
from sssjax.transport.gather import R0_MM, disc_node_weights, gather_cloud

ROOT = Path(__file__).resolve().parent.parent


def test_near_field_weights_integrate_the_profile_exactly(x64):
    # sum_b w_b R_d(r_b) = int_0^R 2 pi r R_d(r) dr, which has a closed form for the dipole
    r_nodes = R0_MM * np.expm1(np.arange(256) * np.log1p(40.0 / R0_MM) / 255)
    du = np.log1p(40.0 / R0_MM) / 255
    for name in ("marble", "skin1", "ketchup"):
        m = preset(name)
        for R in (0.3, 1.2, 5.0):
            w = disc_node_weights(r_nodes, R0_MM, du, R)
            got = w @ np.asarray(dipole.Rd(r_nodes[:, None], m.sigma_a, m.sigmap_s, 1.3))
            sp_t = np.asarray(m.sigmap_t)
            s_tr = np.asarray(m.sigma_tr)
            ap = np.asarray(m.alpha_p)
            A = float(dipole.A_boundary(1.3))
            exact = 0.0
            for z in (1 / sp_t, (1 + 4 * A / 3) / sp_t):
                dR = np.sqrt(R**2 + z**2)
                exact = exact + ap / 2 * (np.exp(-s_tr * z) - z * np.exp(-s_tr * dR) / dR)
            np.testing.assert_allclose(got, exact, rtol=2e-3)


def test_gather_histogram_matches_dense_sum(x64):
    """The trace-time distance nodes reproduce the exact sum over the cloud (far field)
    plus the flat-disc near field, for arbitrary coefficients (not those traced with)."""
    scene = slab_scene({"type": "translucent", "preset": "skin1"}, cloud=4096)
    r = Renderer(scene)
    tr = r.transport
    cloud = r.image_state(as_key(0, scene))
    P, S = 6, scene.render.spp
    M = P * S
    key = jax.random.key(3)
    xo = jnp.concatenate(
        [
            jax.random.uniform(key, (M, 1), minval=-25, maxval=25),
            jnp.zeros((M, 1)),
            jax.random.uniform(jax.random.key(4), (M, 1), minval=-25, maxval=25),
        ],
        axis=1,
    )
    have = jnp.ones(M, bool)
    cos_o = jnp.full(M, 0.8)
    tobj = jnp.zeros(M, jnp.int32)
    T = jnp.ones((M, 3))
    E_o = jnp.full((M, 3), 2.0)
    slots = dict(have=have, xo=xo, cos_o=cos_o, tobj=tobj, T_slot=T, E_o=E_o)
    hist = gather_cloud(r.arrays, tr.nodes, cloud, slots, P, S)
    R = tr.nodes.r_near[0]
    n_sub = tr.cloud_n // S
    Ft = float(dipole.fresnel_transmittance(0.8, 1.3))
    for med in (preset("skin1"), preset("marble"), Medium([0.3, 0.1, 0.05], [1.0, 2.0, 4.0])):
        rd_nodes = dipole.Rd(jnp.asarray(tr.nodes.r_nodes)[:, None], med.sigma_a, med.sigmap_s, 1.3)
        via_hist = jnp.einsum("pbc,bc->pc", hist[0], rd_nodes)
        dense = np.zeros((P, 3))
        for s in range(M):
            p, j = s // S, s % S
            pts = cloud.points[0, j::S]
            E = cloud.irradiance[0, j::S]
            assert pts.shape[0] == n_sub
            d = jnp.linalg.norm(pts - xo[s], axis=-1)
            far = (d >= R)[:, None]
            rd = dipole.Rd(d[:, None], med.sigma_a, med.sigmap_s, 1.3)
            far_sum = jnp.sum(jnp.where(far, rd * E, 0.0), axis=0) * cloud.area[0] * S
            # near field, closed form
            near = 0.0
            A = float(dipole.A_boundary(1.3))
            for z in (1 / med.sigmap_t, (1 + 4 * A / 3) / med.sigmap_t):
                dR = jnp.sqrt(R**2 + z**2)
                near = near + med.alpha_p / 2 * (
                    jnp.exp(-med.sigma_tr * z) - z * jnp.exp(-med.sigma_tr * dR) / dR
                )
            dense[p] += np.asarray((far_sum + near * E_o[s]) * Ft / np.pi / S)
        np.testing.assert_allclose(via_hist, dense, rtol=3e-3)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "profile"),
    [("skin1", "dipole"), ("ketchup", "dipole"), ("skin1", "better_dipole"), ("skin1", "pbd")],
)
def test_flat_slab_multiple_scattering_approaches_closed_form(name, profile):
    """Far from the slab's edges, under (nearly) uniform light from straight above, the
    multiple-scattering radiance is F_t(cos_o)/pi * E_t * R_d,total (Jensen 2001 eq. 4-5),
    with E_t the Fresnel-transmitted irradiance and R_d,total that of the scene's profile.
    Single scattering is off here."""
    scene = slab_scene({"type": "translucent", "preset": name}).with_settings(sss_profile=profile)
    img = sssjax.render(scene, 0)
    m = preset(name)
    d = 1000.0
    E_t = 1e6 / d**2 * float(dipole.fresnel_transmittance(1.0, 1.3))
    cam = scene.camera
    v = cam.origin - cam.target
    cos_o = v[1] / np.linalg.norm(v)
    expected = (
        float(dipole.fresnel_transmittance(cos_o, 1.3))
        / np.pi
        * E_t
        * np.asarray(profiles.Rd_total(m.sigma_a, m.sigmap_s, m.eta, profile))
    )
    if profile != "dipole":  # the test tells the profiles apart: skin1's blue differs by > 20%
        classic = np.asarray(dipole.Rd_total(m.sigma_a, m.sigmap_s, m.eta))
        own = np.asarray(profiles.Rd_total(m.sigma_a, m.sigmap_s, m.eta, profile))
        assert np.max(np.abs(own / classic - 1)) > 0.2
    got = img.reshape(-1, 3).mean(axis=0)
    # the light is 1 m away: irradiance falls by < 0.1% over the diffusion lengths involved
    np.testing.assert_allclose(got, expected, rtol=0.03)


def test_single_scattering_adds_light_and_is_positive():
    scene = slab_scene({"type": "translucent", "preset": "skin1"}, single=True, cloud=2048)
    with_ss = sssjax.render(scene, 0)
    without = sssjax.render(scene.with_settings(sss_single_scattering=False), 0)
    assert np.all(with_ss >= without - 1e-6)
    assert np.all(with_ss.mean(axis=(0, 1)) > without.mean(axis=(0, 1)))


@pytest.mark.slow
def test_milk_cylinder_shaded_side_brighter_with_sss():
    scene = sssjax.load_scene(ROOT / "scenes" / "milk_cylinder.toml").with_settings(
        width=48, height=48, spp=4, sss_cloud_size=4096, light_samples=2
    )
    on = sssjax.render(scene, 0)
    off = sssjax.render(scene.with_settings(sss_enabled=False), 0)
    # surface points on the side facing away from the light (which is at -x), above the table
    phi = np.radians([30.0, 45.0, 60.0])
    pts = np.array([[15 * np.cos(f), y, 15 * np.sin(f)] for f in phi for y in (12.0, 25.0)])
    xy = np.asarray(project(scene.camera, pts)).astype(int)
    for x, y in xy:
        assert on[y, x].sum() > 2 * off[y, x].sum() + 1e-3


def test_render_gradients_match_central_differences(x64):
    scene = slab_scene(
        {"type": "translucent", "preset": "marble", "scale": 4.0},
        width=4,
        spp=4,
        cloud=1024,
        single=True,
    )
    base = scene.media()["m"]

    def loss(p):
        med = Medium(p[:3], p[3:], base.g, base.eta)
        return jnp.sum(sssjax.render(scene, 0, media={"m": med}) ** 2)

    p0 = jnp.concatenate([base.sigma_a, base.sigma_s]).astype(jnp.float64)
    g = jax.grad(loss)(p0)
    J = jax.jacfwd(loss)(p0)
    assert np.all(np.isfinite(g))
    fd = central_differences(lambda p: loss(jnp.asarray(p)), p0)
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    np.testing.assert_allclose(J, fd, rtol=1e-5)


def test_shade_of_trace_equals_render():
    scene = slab_scene({"type": "translucent", "preset": "skin2"}, single=True, cloud=2048)
    img = sssjax.render(scene, 5)
    tr = sssjax.trace(scene, 5)
    np.testing.assert_allclose(sssjax.shade_image(tr, scene.media()), img, rtol=1e-5, atol=1e-7)


def test_profile_reaches_render_trace_shade_and_fit_blocks():
    # the scene's [sss] profile is used by render's fused trace+shade, recorded in the
    # transport (and its SSSBlock, which the fit shades), and it changes the image
    base = slab_scene({"type": "translucent", "preset": "skin1"}, cloud=2048)
    scene = base.with_settings(sss_profile="better_dipole")
    img = sssjax.render(scene, 5)
    tr = sssjax.trace(scene, 5)
    assert tr.profile == "better_dipole" and tr.sss_terms().profile == "better_dipole"
    np.testing.assert_allclose(sssjax.shade_image(tr, scene.media()), img, rtol=1e-5, atol=1e-7)
    media = tuple(scene.media()[n] for n in tr.materials)
    via_block = shade_sss(tr.sss_terms(), media, tr.r_nodes)
    np.testing.assert_allclose(via_block, shade_sss(tr, media, tr.r_nodes), rtol=1e-6)
    classic = sssjax.render(base, 5)
    # skin1's green and blue totals differ by 15% and 21% between the two profiles
    ratio = img.reshape(-1, 3).mean(0) / classic.reshape(-1, 3).mean(0)
    expected = np.asarray(
        profiles.Rd_total(media[0].sigma_a, media[0].sigmap_s, 1.3, "better_dipole")
    ) / np.asarray(dipole.Rd_total(media[0].sigma_a, media[0].sigmap_s, 1.3))
    np.testing.assert_allclose(ratio, expected, rtol=0.03)


def test_determinism_by_seed():
    scene = slab_scene({"type": "translucent", "preset": "skin2"}, single=True, cloud=2048)
    a = sssjax.render(scene, 1)
    b = sssjax.render(scene, 1)
    c = sssjax.render(scene, 2)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 0


@pytest.mark.slow
def test_one_and_two_devices_give_the_same_image(tmp_path):
    script = textwrap.dedent(
        f"""
        import jax, numpy as np, sssjax
        assert jax.device_count() == 2, jax.devices()
        scene = sssjax.load_scene({str(ROOT / "scenes" / "marble_cube.toml")!r}).with_settings(
            width=40, height=40, spp=4, sss_cloud_size=2048, light_samples=2, tile=8)
        two = sssjax.render(scene, 0)
        one = sssjax.render(scene, 0, devices=jax.devices()[:1])
        np.testing.assert_allclose(two, one, rtol=1e-6, atol=1e-7)
        assert two.max() > 0
        print("same")
        """
    )
    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu"
    )
    p = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600
    )
    assert p.returncode == 0, p.stderr[-3000:]
    assert "same" in p.stdout


def _ms_mean(scene, seed=0):
    tr = sssjax.trace(scene, seed)
    img = sssjax.shade(tr, scene.media(), single=False)
    return np.asarray(img), tr


@pytest.mark.slow
def test_strategies_agree_with_cloud_within_noise():
    """The per-pixel Monte Carlo strategies and the irradiance cloud estimate the same
    integral; `within` with a radius beyond the object equals `uniform`; the two halves of
    an annulus split add up to the whole."""
    mat = {"type": "translucent", "preset": "skin1"}
    kw = dict(width=6, spp=16, size=30.0, thick=8.0, light_height=300.0, intensity=1e5)
    cloud, _ = _ms_mean(slab_scene(mat, cloud=16384, **kw))
    ests = {}
    for name, sss in {
        "uniform": {"strategy": "uniform", "samples": 64},
        "within": {"strategy": "within", "radius": 100.0, "samples": 64, "tries": 2},
        "near": {"strategy": "annulus", "inner": 0.0, "outer": 3.0, "samples": 64, "tries": 8},
        "far": {"strategy": "annulus", "inner": 3.0, "outer": 100.0, "samples": 64, "tries": 2},
    }.items():
        sc = slab_scene(mat, cloud=1024, **kw)
        sc = sc.replace(sss=sc.sss.__class__(**{**sc.sss.__dict__, **sss}))
        ests[name], _ = _ms_mean(sc)
    ref = cloud.mean(axis=0)

    def check(img, what):
        # every pixel looks at the middle of the slab: treat pixels as independent estimates
        mean, se = img.mean(axis=0), img.std(axis=0) / np.sqrt(img.shape[0])
        assert np.all(np.abs(mean - ref) < 4 * se + 0.02 * ref), (what, mean, ref, se)

    check(ests["uniform"], "uniform")
    check(ests["within"], "within")
    check(ests["near"] + ests["far"], "near + far")
    assert np.all(ests["near"].mean(axis=0) > ests["far"].mean(axis=0))  # R_d is peaked
