"""Bounded memory: camera rays are made per tile, the image is the one per-pixel array.

A render must not materialise anything for the whole image but the image itself: camera
rays are generated inside each block's trace (for the block's pixels only), tiles are
traced one group at a time, and the host-side image is preallocated and filled in place.
"""

import importlib
import sys
import tracemalloc
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import sssjax
import sssjax.camera
from sssjax.render import renderer_for
from sssjax.scene import load_scene
from sssjax.transport import NO_RECORD, Block, TransportMethod

DATA = Path(__file__).parent / "data"
render_module = importlib.import_module("sssjax.render")  # `sssjax.render` is the function


def _spy_camera_rays(monkeypatch) -> list:
    """Replace `camera_rays` everywhere sssjax imported it; returns the pixel shapes of its
    calls (calls happen while tracing: one per compiled block program)."""
    real = sssjax.camera.camera_rays
    seen = []

    def spy(cam, pixel, jitter):
        seen.append(tuple(pixel.shape))
        return real(cam, pixel, jitter)

    for name, mod in list(sys.modules.items()):
        if name.startswith("sssjax") and getattr(mod, "camera_rays", None) is real:
            monkeypatch.setattr(mod, "camera_rays", spy)
    return seen


def _count_blocks(monkeypatch, r) -> list:
    """Wrap the renderer's compiled block programs: the pixel-index shapes of their calls."""
    calls = []
    for attr in ("_block", "_block_shaded"):
        fn = getattr(r, attr)

        def counted(arrays, state, pix, *rest, fn=fn):
            calls.append(tuple(pix.shape))
            return fn(arrays, state, pix, *rest)

        monkeypatch.setattr(r, attr, counted)
    return calls


def test_camera_rays_are_made_per_tile(monkeypatch):
    """A 96 x 40 image in 8 x 8 tiles: rays for 64 pixels at a time, in 60 block calls."""
    seen = _spy_camera_rays(monkeypatch)
    scene = load_scene(DATA / "tiny_scene.toml").with_settings(width=96, height=40, tile=8)
    r = renderer_for(scene)
    calls = _count_blocks(monkeypatch, r)
    img = sssjax.render(scene, 0)
    assert img.shape == (40, 96, 3) and np.isfinite(img).all() and img.max() > 0
    assert seen, "the transport did not make its camera rays through camera_rays"
    assert set(seen) == {(64,)}, seen  # never the whole image's 3840 pixels
    D = jax.device_count()
    assert len(calls) == -(-60 // D) and set(calls) == {(D, 64)}


class _CameraOnly(TransportMethod):
    """A stub transport whose radiance is the direction of the ray through each pixel's
    centre: cheap to compile and run, and a closed form to check the tiling against."""

    name = "camera_only"

    def __init__(self, arrays):
        self.arrays = arrays

    @property
    def media_dependent(self) -> bool:
        return False

    def empty_terms(self):
        return None

    def trace_block(self, arrays, state, pixels, key, rec=NO_RECORD):
        P = pixels.shape[0]
        _, d = sssjax.camera.camera_rays(arrays.camera, pixels, jnp.full((P, 1, 2), 0.5))
        return Block(base=d[:, 0], needs=jnp.zeros(P, bool), rows=None)


class _Only:
    @staticmethod
    def get_entry(name):
        return _CameraOnly


def test_host_memory_is_the_image_plus_a_chunk(monkeypatch):
    """A 1024 x 1024 image in 64 x 64 tiles through a stub transport: every pixel gets its
    own ray (a closed form), the rays are made per tile, and the host allocations stay
    within the image (12 bytes a pixel) plus a chunk of 4 tiles: nothing else per pixel of the
    whole image (its pixel indices alone would be 8 bytes a pixel, its rays 24)."""
    monkeypatch.setattr(render_module, "TRANSPORTS", _Only)
    monkeypatch.setattr(render_module, "CHUNK_TILES", 4)  # a chunk of 1/16 of the image
    seen = _spy_camera_rays(monkeypatch)
    n = 1024
    scene = load_scene(DATA / "tiny_scene.toml").with_settings(width=n, height=n, tile=64)
    r = render_module.Renderer(scene)
    assert isinstance(r.transport, _CameraOnly)
    media = tuple(scene.media()[m] for m in r.arrays.materials)
    r.render(0, media, progress=False)  # compile outside the measurement
    tracemalloc.start()
    img = r.render(0, media, progress=False)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert set(seen) == {(64 * 64,)}, seen
    assert img.shape == (n, n, 3) and img.nbytes == 12 * n * n
    rows = np.array([0, 1, 63, 64, 500, n - 1])
    pix = (rows[:, None] * n + rows[None, :]).reshape(-1)  # tile corners and edges
    _, d = sssjax.camera.camera_rays(
        scene.camera, jnp.asarray(pix), jnp.full((len(pix), 1, 2), 0.5)
    )
    np.testing.assert_allclose(img.reshape(-1, 3)[pix], np.asarray(d[:, 0]), atol=1e-6)
    # the image, plus a chunk of tiles (pixel indices, radiance, their concatenation and
    # deduplication: about 65 bytes a pixel of the chunk, measured)
    chunk = render_module.CHUNK_TILES * 64 * 64 * 100
    assert peak < img.nbytes + chunk, (peak, img.nbytes)
