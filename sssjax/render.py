"""Rendering a whole image: tiles, devices, packing, progress. `render = shade . trace`.

The scene becomes `SceneArrays` once; its transport (`TRANSPORTS[scene.sss.transport]`)
traces fixed-size blocks of pixels. Memory is bounded by the tile size: a tile of
`tile x tile` pixels is traced, shaded and dropped before the next. Tiles are processed in
groups of one per JAX device, sharded over all devices with `jax.sharding` (each tile's
random key is derived from the seed and the tile index only, so the image does not depend
on the number of devices). A two-phase transport's second phase runs on the rows that need
it, packed into full blocks. The arrays are an argument of every compiled function, so a
refractive index or a light's emission changes without recompiling.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._arrays import SceneArrays
from ._budget import check_memory
from ._progress import Progress
from .media import Medium
from .scene import Scene
from .shade import shade_image
from .transport import TRANSPORTS, Terms, Transport

__all__ = ["render", "trace", "Renderer", "renderer_for", "as_key"]


def as_key(key, scene: Scene):
    """A `jax.random` key from a key, an integer seed, or `None` (the scene's seed)."""
    if key is None:
        key = scene.render.seed
    if isinstance(key, int | np.integer):
        return jax.random.key(int(key))
    return key


CHUNK_TILES = 16  # tiles per chunk: the unit of host-side packing (bounds host memory)


def _take(rows, idx):
    """Rows `idx` of a per-row pytree: `Terms.rows`, or indexing every leaf."""
    if isinstance(rows, Terms):
        return rows.rows(idx)
    return jax.tree_util.tree_map(lambda v: v[idx], rows)


def _concat(parts: list):
    """Per-row pytrees one after the other."""
    if isinstance(parts[0], Terms):
        return type(parts[0]).concat(parts)
    return jax.tree_util.tree_map(lambda *v: np.concatenate(v), *parts)


class Renderer:
    """A scene's arrays and compiled transport, plus the tiling, packing and device layout.

    Rendering runs in chunks of `CHUNK_TILES` tiles: `trace_block` on every tile, then, for
    a two-phase transport, `trace_rows` on the rows that need it packed into blocks of one
    tile's size. Each tile and block gets a key folded from the seed and its index, so
    images do not depend on the number of devices.
    """

    def __init__(self, scene: Scene, devices=None):
        check_memory(scene)  # one line before allocating, for a render that cannot fit
        self.scene = scene
        self.arrays = SceneArrays.from_scene(scene)
        self.transport = TRANSPORTS.get_entry(scene.sss.transport)(self.arrays)
        self.devices = list(devices) if devices is not None else jax.devices()
        self.mesh = Mesh(np.array(self.devices), ("tiles",))
        self.sharding = NamedSharding(self.mesh, PartitionSpec("tiles"))
        cam = scene.camera
        self.n_pixels = cam.width * cam.height
        # pixels per block: a tile, or what the transport asks for (walks need wide blocks)
        self.block = min(self.transport.block_pixels(scene.render.tile), self.n_pixels)
        self.n_blocks = -(-self.n_pixels // self.block)
        tm = self.transport
        tiles, whole = PartitionSpec("tiles"), PartitionSpec()
        # the walks of a re-weighting transport are run-bound: LLVM O3 whatever XLA_FLAGS say
        # (the test suite compiles at O0, where the walks ran several times slower)
        opt = {"xla_backend_optimization_level": 3} if tm.reweighted else None

        def sharded(fn, n_rest: int = 0):
            # one tile per device, each run as its own program (not vmapped: a vmapped
            # `switch` would run every branch, and the chains skip the bounces of dead rays)
            def per_device(arrays, state, pix, keys, *rest):
                out = fn(arrays, state, pix[0], keys[0], *rest)
                return jax.tree_util.tree_map(lambda a: a[None], out)

            specs = (whole, whole, tiles, tiles) + (whole,) * n_rest
            return jax.jit(
                jax.shard_map(
                    per_device, mesh=self.mesh, in_specs=specs, out_specs=tiles, check_vma=False
                ),
                compiler_options=opt,
            )

        def block(arrays, state, pix, key):
            return tuple(tm.trace_block(arrays, state, pix, key))

        def block_shaded(arrays, state, pix, key, media):
            base, needs, terms = tm.trace_block(arrays, state, pix, key)
            return base + jnp.where(needs[:, None], terms.shade(media), 0.0)

        self._block = sharded(block)
        self._block_shaded = sharded(block_shaded, n_rest=1)
        self._state = jax.jit(tm.image_state)

        def rows(arrays, state, blk, valid, keys):
            return jax.vmap(lambda b, v, k: tm.trace_rows(arrays, state, b, v, k))(blk, valid, keys)

        def rows_shaded(arrays, state, blk, valid, keys, media):
            def one(b, v, k):
                return tm.trace_rows(arrays, state, b, v, k).shade(media)

            return jax.vmap(one)(blk, valid, keys)

        self._rows = jax.jit(rows, compiler_options=opt)
        self._rows_shaded = jax.jit(rows_shaded, compiler_options=opt)

    @property
    def D(self) -> int:
        return len(self.devices)

    def _put(self, x):
        return jax.device_put(x, self.sharding)

    def _keys(self, key, idx):
        return self._put(jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.asarray(idx)))

    def arrays_for(self, etas: Mapping | None = None, gain=None) -> SceneArrays:
        """The scene's arrays with translucent materials' refractive indices `etas` (by
        name; geometry: they bend rays) and each light's emission times `gain` (one factor
        per light, scene order)."""
        return self.arrays.with_eta(etas).with_gain(gain)

    def image_state(self, key, arrays: SceneArrays | None = None):
        """The transport's state shared by every block of the image of `key` (the diffusion
        transport's irradiance cloud)."""
        return self._state(self.arrays if arrays is None else arrays, as_key(key, self.scene))

    def chunks(self, key, progress_label: str | None, arrays, state, media=None):
        """Trace every tile, in chunks. Yields `(pixels, base, needs, rows)` per chunk (host
        arrays, one row per pixel; see `Block`). With `media` (one-phase transports only)
        `base` is the shaded radiance and `rows` None."""
        k_tiles = jax.random.fold_in(key, 1)
        bar = Progress(self.n_blocks, progress_label or "", progress_label is not None)
        step = max(CHUNK_TILES, self.D) // self.D * self.D
        for c0 in range(0, self.n_blocks, step):
            pix_l, base_l, needs_l, rows_l = [], [], [], []
            for g0 in range(c0, min(c0 + step, self.n_blocks), self.D):
                idx = np.arange(g0, g0 + self.D)
                starts = np.minimum(idx, self.n_blocks - 1) * self.block
                pix = starts[:, None] + np.arange(self.block)[None, :]
                pix = np.minimum(pix, self.n_pixels - 1).astype(np.int32)
                args = (arrays, state, self._put(jnp.asarray(pix)), self._keys(k_tiles, idx))
                n = min(self.D, self.n_blocks - g0)
                if media is None:
                    base, needs, rows = self._block(*args)
                    needs_l.append(np.asarray(needs)[:n].reshape(-1))
                    host = jax.tree_util.tree_map(np.asarray, rows)
                    rows_l += [jax.tree_util.tree_map(lambda a, i=i: a[i], host) for i in range(n)]
                else:
                    base = self._block_shaded(*args, media)
                pix_l.append(pix[:n].reshape(-1))
                base_l.append(np.asarray(base)[:n].reshape(-1, 3))
                bar.update(g0 + n)
            pix = np.concatenate(pix_l)
            # the last tile is padded with repeats of the last pixel: keep the first copy
            pix, first = np.unique(pix, return_index=True)
            base = np.concatenate(base_l)[first]
            if media is not None:
                yield pix, base, np.zeros(len(pix), bool), None
                continue
            yield pix, base, np.concatenate(needs_l)[first], _take(_concat(rows_l), first)

    def packed(self, key, needs: np.ndarray, rows, counter: list[int]):
        """A two-phase transport's second-phase input: the rows that `need` it, packed into
        blocks. Yields `(row indices (D, block), valid (D, block), rows (D, block, ...),
        valid on the devices, keys)`."""
        sel = np.flatnonzero(needs)
        nb = -(-len(sel) // self.block)
        k_rows = jax.random.fold_in(key, 2)
        for g0 in range(0, nb, self.D):
            idx = np.arange(g0, g0 + self.D)
            pos = idx[:, None] * self.block + np.arange(self.block)[None, :]
            valid = pos < len(sel)
            r = np.where(valid, sel[np.minimum(pos, max(len(sel) - 1, 0))], 0)
            blk = jax.tree_util.tree_map(lambda v: self._put(jnp.asarray(v[r])), rows)
            keys = self._keys(k_rows, counter[0] + idx)
            yield r, valid, blk, self._put(jnp.asarray(valid)), keys
        counter[0] += nb

    def render(self, key, media, progress: bool) -> np.ndarray:
        """The `(H, W, 3)` image for `media` (one `Medium` per translucent material, in
        `arrays.materials` order; their `eta` bends the rays as well as entering the
        profile)."""
        key = as_key(key, self.scene)
        media = tuple(media)
        tm = self.transport
        img = np.zeros((self.n_pixels, 3), jnp.result_type(float))  # float64 under x64
        arrays = self.arrays_for(
            {n: m.eta for n, m in zip(self.arrays.materials, media, strict=True)}
        )
        if tm.reweighted:  # sample the walks with the media rendered (no re-weighting)
            arrays = arrays.with_media(media)
        state = self.image_state(key, arrays)
        fused = None if tm.two_phase or not tm.media_dependent else media
        counter = [0]
        label = "rendering" if progress else None
        for pix, base, needs, rows in self.chunks(key, label, arrays, state, fused):
            img[pix] = base
            if not (tm.two_phase and tm.media_dependent):
                continue
            for r, valid, blk, valid_d, keys in self.packed(key, needs, rows, counter):
                L = np.asarray(self._rows_shaded(arrays, state, blk, valid_d, keys, media))
                img[pix[r[valid]]] += L[valid]
        cam = self.scene.camera
        return img.reshape(cam.height, cam.width, 3)

    def trace(
        self,
        key,
        progress: bool = False,
        etas: Mapping | None = None,
        gain=None,
        proposal: Mapping | None = None,
        keep=None,
    ):
        """The `Transport` of the whole image; `etas` overrides translucent materials'
        refractive index by name (geometry: it bends rays) and `gain` multiplies each
        light's emission (one factor per light, scene order), without recompiling.
        `proposal` (media by material name) replaces the media a re-weighting transport
        samples its walks with (`TransportMethod.reweighted`; the others ignore it).
        `keep` (flat boolean per image pixel; one-phase transports) gives these pixels
        terms rows even where no sample reached a medium (zero terms): a fit's rows then
        do not depend on where this trace's samples happened to land."""
        key = as_key(key, self.scene)
        tm = self.transport
        arrays = self.arrays_for(etas, gain)
        if proposal and tm.reweighted:
            arrays = arrays.with_media(proposal)
        state = self.image_state(key, arrays)
        counter = [0]
        pix_all, base_all, rows_all, parts = [], [], [], []
        offset = 0
        for pix, base, needs, rows in self.chunks(
            key, "tracing" if progress else None, arrays, state
        ):
            pix_all.append(pix)
            base_all.append(base)
            if not tm.media_dependent:
                pass
            elif not tm.two_phase:
                sel = np.flatnonzero(needs if keep is None else needs | keep[pix])
                rows_all.append(offset + sel)
                parts.append(rows.rows(sel))
            else:
                for r, valid, blk, valid_d, keys in self.packed(key, needs, rows, counter):
                    out = jax.tree_util.tree_map(
                        np.asarray, self._rows(arrays, state, blk, valid_d, keys)
                    )
                    for i in range(r.shape[0]):
                        if valid[i].any():
                            rows_all.append(offset + r[i][valid[i]])
                            one = jax.tree_util.tree_map(lambda a, i=i: a[i], out)
                            parts.append(one.rows(np.flatnonzero(valid[i])))
            offset += len(pix)
        terms = type(parts[0]).concat(parts) if parts else tm.empty_terms()
        terms = jax.tree_util.tree_map(jnp.asarray, terms)
        t_rows = np.concatenate(rows_all) if rows_all else np.zeros(0, np.int64)
        return Transport(
            pixels=jnp.asarray(np.concatenate(pix_all)),
            base=jnp.asarray(np.concatenate(base_all)),
            t_rows=jnp.asarray(t_rows.astype(np.int32)),
            terms=terms,
            width=self.scene.camera.width,
            height=self.scene.camera.height,
            materials=self.arrays.materials,
        )


_CACHE: list[tuple[Scene, tuple, Renderer]] = []


def renderer_for(scene: Scene, devices=None) -> Renderer:
    """The compiled `Renderer` of `scene`, reused across calls (the 8 most recent scenes).

    Scenes are immutable, so the same object always means the same renderer; `with_settings`
    returns a new scene (and so a new renderer)."""
    devs = tuple(devices) if devices is not None else tuple(jax.devices())
    for sc, dv, r in _CACHE:
        if sc is scene and dv == devs:
            return r
    r = Renderer(scene, devs)
    _CACHE.insert(0, (scene, devs, r))
    del _CACHE[8:]
    return r


def trace(scene: Scene, key=None, *, progress: bool = False) -> Transport:
    """The geometric pass over the whole image: `render = shade . trace`.

    **Arguments:** `scene` from `load_scene`; `key` a `jax.random` key or an integer seed
    (default: the scene's `render.seed`); `progress`: a progress bar over tiles on stderr.

    **Returns:** a `Transport` for every pixel (its memory grows with the image: for large
    images use `render`, which traces and shades tile by tile).
    """
    return renderer_for(scene).trace(key, progress)


def render(
    scene: Scene,
    key=None,
    media: Mapping[str, Medium] | None = None,
    *,
    seed: int | None = None,
    progress: bool = False,
    devices=None,
) -> np.ndarray:
    """Render `scene` to a `(height, width, 3)` linear-RGB radiance image.

    **Arguments:**

    - `scene`: from `load_scene`. Lengths in mm, coefficients in mm^-1.
    - `key`: a `jax.random` key or integer seed (default: the scene's `render.seed`);
      `seed=` is the same, by name (give one of them).
    - `media`: override the translucent materials' media (dict by material name).
    - `progress`: print a progress bar over tiles to stderr.
    - `devices`: JAX devices to shard tiles over (default: all).

    **Returns:** a NumPy image (float32; float64 under `jax.enable_x64`). Same scene, seed and settings give the same image.
    Under `jax.grad` / `jax.jacfwd` with respect to `media` it returns a JAX array
    (`shade_image(trace(scene, key), media)`: the trace is fixed, the shading differentiated).
    """
    if seed is not None:
        if key is not None:
            raise TypeError("render: give the seed as `key` or as `seed=`, not both")
        key = seed
    r = renderer_for(scene, devices)
    m = dict(scene.media())
    if media:
        unknown = set(media) - set(m)
        if unknown:
            raise ValueError(
                f"render: no translucent material named {sorted(unknown)} in the scene "
                f"(translucent materials: {', '.join(m) or 'none'})"
            )
        m.update(media)
    ordered = tuple(m[n] for n in r.arrays.materials)
    leaves = jax.tree_util.tree_leaves(ordered)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        # under jax.grad / jacfwd / vmap: the differentiable path, shade(trace(scene)); the
        # media's eta bends the rays of the trace too, unless it is being differentiated
        etas = {
            n: float(md.eta)
            for n, md in zip(r.arrays.materials, ordered, strict=True)
            if not isinstance(md.eta, jax.core.Tracer)
        }
        return shade_image(r.trace(key, progress, etas), ordered)
    return r.render(key, ordered, progress)
