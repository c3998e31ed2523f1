"""The transport interface: a one-phase transport plugs into render, trace, shade, fit and
the ray tree through `TRANSPORTS` and the terms protocol alone; the scene's `[sss]
transport` is validated; eta and light gains are arguments of the compiled functions (no
recompilation); and the package has no import cycle."""

from __future__ import annotations

import ast
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import shipped_scene, small_cube
from jaxtyping import Array, Float

import sssjax
from sssjax import profiles
from sssjax.render import renderer_for
from sssjax.scene import SceneError
from sssjax.transport import NO_RECORD, TRANSPORTS, Block, Prepared, Terms, TransportMethod
from sssjax.transport.chains import chain_block

PACKAGE = Path(sssjax.__file__).resolve().parent
TINT = jnp.array([1.0, 2.0, 3.0])


# --- a one-phase toy transport ------------------------------------------------------------
class ToyTerms(Terms):
    """Per row a weight `w (3,)` times the diffusion total `Rd_total` of the medium."""

    w: Float[Array, "P 3"]

    def rows(self, idx):
        return ToyTerms(self.w[idx])

    @classmethod
    def concat(cls, parts):
        return ToyTerms(jnp.concatenate([p.w for p in parts]))

    @classmethod
    def mean(cls, parts):
        return ToyTerms(sum(p.w for p in parts) / len(parts))

    def prepare(self, etas):
        return ToyShading(self.w)


class ToyShading(Prepared):
    w: Float[Array, "P 3"]

    def shade(self, media, **options):
        m = media[0]
        return self.w * profiles.Rd_total(m.sigma_a, m.sigmap_s, m.eta)


class Toy(TransportMethod):
    """The diffusion chains without subsurface light for `base`, and on every even pixel
    a media term `w = (pixel + 1) sum(gain) (1, 2, 3) / 1000`: all in one phase."""

    name = "toy"

    def __init__(self, arrays):
        self.materials = arrays.materials

    @property
    def media_dependent(self):
        return True

    def empty_terms(self):
        return ToyTerms(jnp.zeros((0, 3)))

    def trace_block(self, arrays, state, pixels, key, rec=NO_RECORD):
        base, _ = chain_block(arrays, pixels, key, subsurface=False, rec=rec)
        needs = pixels % 2 == 0
        w = (pixels[:, None] + 1.0) * jnp.sum(arrays.gain) * TINT / 1000.0
        return Block(base, needs, ToyTerms(jnp.where(needs[:, None], w, 0.0)))


TRANSPORTS.register("toy", Toy)


def toy_scene(transport="toy"):
    # 20 x 14 pixels in tiles of 8 x 8: the last tile is padded (280 = 4 x 64 + 24)
    base = small_cube("marble", width=20, height=14, spp=1, tile=8, light_samples=1)
    return base.with_settings(sss_transport=transport, sss_cloud_size=64)


def expected_toy(scene, media=None, gain=1.0):
    """The toy's image in closed form: the render without subsurface light plus the term."""
    cam = scene.camera
    base = sssjax.render(scene.with_settings(sss_transport="diffusion", sss_enabled=False), 0)
    m = (media or scene.media())["marble"]
    pix = np.arange(cam.width * cam.height)
    w = np.where((pix % 2 == 0)[:, None], (pix[:, None] + 1.0) * gain * np.asarray(TINT), 0.0)
    rd = np.asarray(profiles.Rd_total(m.sigma_a, m.sigmap_s, m.eta))
    return np.asarray(base) + (w / 1000.0 * rd).reshape(cam.height, cam.width, 3)


@pytest.fixture(scope="module")
def toy():
    scene = toy_scene()
    return scene, expected_toy(scene)


def test_one_phase_transport_renders_traces_and_shades(toy):
    scene, want = toy
    img = sssjax.render(scene, 0)
    np.testing.assert_allclose(img, want, rtol=1e-5, atol=1e-7)
    tr = sssjax.trace(scene, 0)
    assert isinstance(tr.terms, ToyTerms) and tr.t_rows.shape[0] == (20 * 14) // 2
    np.testing.assert_allclose(sssjax.shade_image(tr, scene.media()), want, rtol=1e-5, atol=1e-7)
    other = sssjax.Medium([0.05, 0.1, 0.2], [1.0, 1.5, 2.0])
    np.testing.assert_allclose(
        sssjax.shade_image(tr, {"marble": other}),
        expected_toy(scene, {"marble": other}),
        rtol=1e-5,
        atol=1e-7,
    )


def test_one_phase_terms_are_fitted_through_the_protocol(toy):
    """The fit shades the toy's terms exactly as the diffusion ones: it recovers sigma_a
    from a 2x start (the target is the toy's own image: the minimum is exact)."""
    scene, want = toy
    true = scene.media()["marble"]
    init = {"sigma_a": np.asarray(true.sigma_a) * 2}
    res = sssjax.fit(scene, want, params=["sigma_a"], init=init, seed=0)
    assert res.converged, res.message
    got = [res.values[f"marble.sigma_a.{c}"] for c in "RGB"]
    np.testing.assert_allclose(got, true.sigma_a, rtol=1e-3)


def test_one_phase_raytree_is_the_rendered_pixel(toy):
    scene, want = toy
    for x, y in ((4, 6), (5, 13)):  # a pixel with a media term, and the padded last tile's
        tree = sssjax.raytree(scene, (x, y), 0)
        assert tree.counts()["camera"] == 1
        np.testing.assert_allclose(tree.radiance, want[y, x], rtol=2e-5, atol=1e-7)


# --- the scene's transport setting -----------------------------------------------------------
def test_transport_setting_is_validated():
    base = shipped_scene("marble_cube").source
    scene = sssjax.load_scene(base)
    assert scene.sss.transport == "diffusion"  # the default
    with pytest.raises(SceneError) as e:
        sssjax.load_scene({**base, "sss": {"transport": "volumetrik"}})
    msg = str(e.value)
    assert msg == (
        "<dict>: [sss] transport: unknown transport 'volumetrik'; did you mean "
        f"'volumetric'? (known: {', '.join(TRANSPORTS.names)})"
    )
    with pytest.raises(ValueError, match="unknown transport 'x'"):
        scene.with_settings(sss_transport="x")
    vol = sssjax.load_scene({**base, "sss": {"transport": "volumetric"}})
    assert vol.sss.transport == "volumetric"


# --- eta and gains are arguments -----------------------------------------------------------
def test_eta_and_light_gain_do_not_recompile():
    scene = small_cube("marble", width=12, height=12, spp=1, sss_cloud_size=128)
    r = renderer_for(scene)
    a = r.trace(0)
    compiled = [f._cache_size() for f in (r._block, r._rows, r._state)]
    assert compiled == [1, 1, 1]
    b = r.trace(0, etas={"marble": 1.45})
    c = r.trace(0, gain=[0.5])
    assert [f._cache_size() for f in (r._block, r._rows, r._state)] == compiled
    # and they act: eta changes the trace, a gain scales it
    assert (
        np.abs(np.asarray(b.ms_hist) - np.asarray(a.ms_hist)).max()
        > 1e-3 * np.abs(np.asarray(a.ms_hist)).max()
    )
    np.testing.assert_allclose(c.ms_hist, 0.5 * np.asarray(a.ms_hist), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(c.base, 0.5 * np.asarray(a.base), rtol=1e-5, atol=1e-9)


def test_scene_arrays_replace_eta_and_gain_as_new_pytrees():
    arrays = renderer_for(small_cube("marble", width=8, height=8)).arrays
    new = arrays.with_eta({"marble": 1.5}).with_gain([2.0])
    i = arrays.tobj_shape[0]
    assert float(new.eta[i]) == pytest.approx(1.5) and float(arrays.eta[i]) == pytest.approx(1.3)
    np.testing.assert_allclose(new.lights.radiance, 2.0 * np.asarray(arrays.lights.radiance))
    assert jnp.asarray(new.eta).shape == arrays.eta.shape
    assert eqx.tree_equal(arrays.with_eta(None).with_gain(None), arrays)
    with pytest.raises(ValueError, match="no translucent material named"):
        arrays.with_eta({"wood": 1.5})
    # the media the trace samples with (the single-scattering proposal's extinction)
    dense = sssjax.Medium([0.1, 0.2, 0.3], [3.0, 4.0, 5.0])
    other = arrays.with_media({"marble": dense})
    assert float(other.object_sigma_t()[0]) == pytest.approx(4.2, rel=1e-6)
    assert float(arrays.object_sigma_t()[0]) == pytest.approx(
        float(np.mean(np.asarray(arrays.media[0].sigma_t))), rel=1e-6
    )
    assert jax.tree_util.tree_structure(other) == jax.tree_util.tree_structure(arrays)


# --- no import cycle ---------------------------------------------------------------------------
def _imports(path: Path, module: str) -> set[str]:
    """The sssjax modules `module` (at `path`) imports, anywhere in it (functions too)."""
    pkg = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            parts = pkg.split(".")
            base = ".".join(parts[: len(parts) - node.level + 1])
            target = f"{base}.{node.module}" if node.module else base
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                out.add(sub if _file(sub) else target)
        elif isinstance(node, ast.ImportFrom | ast.Import):
            names = (
                [node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
            )
            out |= {n for n in names if n and n.split(".")[0] == "sssjax"}
    return {m for m in out if m != module}


def _file(module: str) -> Path | None:
    rel = Path(*module.split(".")[1:])
    for p in (PACKAGE / rel / "__init__.py", PACKAGE / f"{rel}.py"):
        if p.exists():
            return p
    return None


def test_no_import_cycle():
    """The module import graph (function-level imports included) is acyclic."""
    graph = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        module = ".".join(parts)
        graph[module] = _imports(path, module)
    assert "sssjax.render" in graph and "sssjax.transport.diffusion" in graph
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*stack, m, n]))
            if n not in state:
                visit(n, [*stack, m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    # nothing below the renderer imports it
    below = [m for m in graph if m.startswith(("sssjax.transport", "sssjax.shade", "sssjax._"))]
    assert not [m for m in below if "sssjax.render" in graph[m]]
