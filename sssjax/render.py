"""Rendering a whole image: tiles, devices, progress. `render = shade . trace`, tile by tile.

Memory is bounded by the tile size: a tile of `tile x tile` pixels is traced, shaded and
dropped before the next. Tiles are processed in groups of one per JAX device, sharded over
all devices with `jax.sharding` (each tile's random key is derived from the seed and the tile
index only, so the image does not depend on the number of devices).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._budget import check_memory
from ._progress import Progress
from .media import Medium
from .scene import Scene
from .shade import shade_image, shade_sss
from .trace import SSS_FIELDS, SceneTracer, Transport

__all__ = ["render", "trace_tiles", "Renderer", "renderer_for", "as_key"]


def as_key(key, scene: Scene):
    """A `jax.random` key from a key, an integer seed, or `None` (the scene's seed)."""
    if key is None:
        key = scene.render.seed
    if isinstance(key, int | np.integer):
        return jax.random.key(int(key))
    return key


class _Progress:
    def __init__(self, total: int, label: str, enabled: bool):
        self.total, self.label, self.enabled = total, label, enabled
        self.t0 = time.perf_counter()

    def update(self, done: int) -> None:
        if not self.enabled:
            return
        frac = done / self.total
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        dt = time.perf_counter() - self.t0
        end = "\n" if done == self.total else ""
        print(
            f"\r{self.label} [{bar}] {done}/{self.total} tiles  {dt:6.1f} s",
            end=end,
            file=sys.stderr,
            flush=True,
        )


CHUNK_TILES = 16  # tiles per chunk: the unit of host-side packing (bounds host memory)


class Renderer:
    """A scene's compiled tracer plus the tiling, packing and device layout.

    Rendering runs in chunks of `CHUNK_TILES` tiles. Phase 1 traces camera paths of every
    tile; phase 2 (the subsurface gather and single scattering, the expensive part) runs only
    on the pixels that see a translucent object, packed into blocks of one tile's size. Each
    tile and block gets a key folded from the seed and its index, so images do not depend on
    the number of devices.
    """

    def __init__(self, scene: Scene, devices=None):
        check_memory(scene)  # one line before allocating, for a render that cannot fit
        self.scene = scene
        self.tracer = SceneTracer(scene)
        self.devices = list(devices) if devices is not None else jax.devices()
        self.mesh = Mesh(np.array(self.devices), ("tiles",))
        self.sharding = NamedSharding(self.mesh, PartitionSpec("tiles"))
        cam = scene.camera
        self.n_pixels = cam.width * cam.height
        self.block = min(scene.render.tile**2, self.n_pixels)
        self.n_blocks = -(-self.n_pixels // self.block)
        tr = self.tracer

        def chain(pix, keys, eta, gain):
            # one tile per device, each run as its own program (not vmapped: a vmapped
            # `switch` would run every branch, and the chain skips the bounces of dead rays)
            base, slots = tr.with_params(tr._chain_block, pix[0], keys[0], eta=eta, gain=gain)
            return base[None], jax.tree_util.tree_map(lambda a: a[None], slots)

        spec = PartitionSpec("tiles")
        self._chain = jax.jit(
            jax.shard_map(
                chain,
                mesh=self.mesh,
                in_specs=(spec, spec, PartitionSpec(), PartitionSpec()),
                out_specs=spec,
                check_vma=False,
            )
        )

        def sss(slots, keys, cloud, eta, gain):
            def one(s, k):
                return tr.with_params(tr._sss_block, s, k, cloud, eta=eta, gain=gain)

            return jax.vmap(one)(slots, keys)

        def sss_shaded(slots, keys, cloud, media, eta, gain):
            blocks = sss(slots, keys, cloud, eta, gain)
            r = jnp.asarray(tr.r_nodes, dtype=float)
            return jax.vmap(lambda b: shade_sss(b, media, r, profile=scene.sss.profile))(blocks)

        self._sss = jax.jit(sss)
        self._sss_shaded = jax.jit(sss_shaded)

    @property
    def D(self) -> int:
        return len(self.devices)

    def _put(self, x):
        return jax.device_put(x, self.sharding)

    def _keys(self, key, idx):
        return self._put(jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.asarray(idx)))

    def cloud(self, key, eta=None, gain=None):
        return self.tracer.cloud(jax.random.fold_in(key, 0x5C0FFEE), eta, gain)

    def chunks(self, key, progress_label: str | None, eta=None, gain=None):
        """Run phase 1 over chunks of tiles. Yields `(pixels, base, slots)` per chunk (host).

        `eta`: per-shape refractive index (`SceneTracer.eta_for`), default the scene's;
        `gain`: per-light emission factors (default 1)."""
        eta = jnp.asarray(self.tracer.eta_for() if eta is None else eta, dtype=float)
        gain = self.tracer.gain_for(gain)
        k_tiles = jax.random.fold_in(key, 1)
        bar = Progress(self.n_blocks, progress_label or "", progress_label is not None)
        step = max(CHUNK_TILES, self.D) // self.D * self.D
        for c0 in range(0, self.n_blocks, step):
            pix_l, base_l, slot_l = [], [], []
            for g0 in range(c0, min(c0 + step, self.n_blocks), self.D):
                idx = np.arange(g0, g0 + self.D)
                starts = np.minimum(idx, self.n_blocks - 1) * self.block
                pix = starts[:, None] + np.arange(self.block)[None, :]
                pix = np.minimum(pix, self.n_pixels - 1).astype(np.int32)
                base, slots = self._chain(
                    self._put(jnp.asarray(pix)), self._keys(k_tiles, idx), eta, gain
                )
                n = min(self.D, self.n_blocks - g0)
                pix_l.append(pix[:n])
                base_l.append(np.asarray(base)[:n])
                slot_l.append({f: np.asarray(v)[:n] for f, v in slots.items()})
                bar.update(g0 + n)
            pix = np.concatenate(pix_l).reshape(-1)
            base = np.concatenate(base_l).reshape(-1, 3)
            slots = {
                f: np.concatenate([s[f] for s in slot_l]).reshape(-1, *slot_l[0][f].shape[2:])
                for f in slot_l[0]
            }
            # the last tile is padded with repeats of the last pixel: keep the first copy
            pix, first = np.unique(pix, return_index=True)
            yield pix, base[first], {f: v[first] for f, v in slots.items()}

    def sss_blocks(self, key, slots: dict, counter: list[int]):
        """Phase 2 input: the rows with a translucent sample, packed into blocks.

        Yields `(rows (D, block), valid (D, block), slots (D, block, spp, ...), keys)`.
        """
        rows = np.flatnonzero(np.any(slots["have"], axis=1))
        nb = -(-len(rows) // self.block)
        k_sss = jax.random.fold_in(key, 2)
        for g0 in range(0, nb, self.D):
            idx = np.arange(g0, g0 + self.D)
            pos = idx[:, None] * self.block + np.arange(self.block)[None, :]
            valid = pos < len(rows)
            r = np.where(valid, rows[np.minimum(pos, max(len(rows) - 1, 0))], 0)
            blk = {f: v[r] for f, v in slots.items()}
            blk["have"] = blk["have"] & valid[:, :, None]
            keys = self._keys(k_sss, counter[0] + idx)
            yield r, valid, {f: self._put(jnp.asarray(v)) for f, v in blk.items()}, keys
        counter[0] += nb

    def render(self, key, media, progress: bool) -> np.ndarray:
        key = as_key(key, self.scene)
        media = tuple(media)
        img = np.zeros((self.n_pixels, 3), jnp.result_type(float))  # float64 under x64
        sss_on = self.tracer.sss_on
        # the media's eta bends the rays as well as entering the profile
        names = self.tracer.tmat_names
        etas = {n: m.eta for n, m in zip(names, media, strict=True)}
        eta = jnp.asarray(self.tracer.eta_for(etas), dtype=float)
        gain = self.tracer.gain_for()
        cloud = self.cloud(key, eta, gain) if sss_on else None
        counter = [0]
        for pix, base, slots in self.chunks(key, "rendering" if progress else None, eta, gain):
            img[pix] = base
            if not sss_on:
                continue
            for rows, valid, blk, keys in self.sss_blocks(key, slots, counter):
                L = np.asarray(self._sss_shaded(blk, keys, cloud, media, eta, gain))
                img[pix[rows[valid]]] += L[valid]
        cam = self.scene.camera
        return img.reshape(cam.height, cam.width, 3)

    def trace(self, key, progress: bool, etas: dict | None = None, gain=None) -> Transport:
        """The transport of the whole image; `etas` overrides translucent materials'
        refractive index by name (geometry: it bends rays) and `gain` multiplies each
        light's emission (one factor per light, scene order), without recompiling."""
        key = as_key(key, self.scene)
        tr = self.tracer
        eta = jnp.asarray(tr.eta_for(etas), dtype=float)
        gain = tr.gain_for(gain)
        cloud = self.cloud(key, eta, gain) if tr.sss_on else None
        counter = [0]
        pix_all, base_all, rows_all, blocks = [], [], [], []
        offset = 0
        for pix, base, slots in self.chunks(key, "tracing" if progress else None, eta, gain):
            pix_all.append(pix)
            base_all.append(base)
            if tr.sss_on:
                for rows, valid, blk, keys in self.sss_blocks(key, slots, counter):
                    out = jax.tree_util.tree_map(np.asarray, self._sss(blk, keys, cloud, eta, gain))
                    for i in range(rows.shape[0]):
                        v = valid[i]
                        if not v.any():
                            continue
                        rows_all.append(offset + rows[i][v])
                        blocks.append(_take_block(out, i, v))
            offset += len(pix)
        Mt, B, K = len(tr.tmat_names), tr.bins, tr.ss_per_sample
        if blocks:
            cat = {
                f: np.concatenate([b[f] for b in blocks], axis=2 if f == "ms_hist" else 0)
                for f in blocks[0]
            }
            t_rows = np.concatenate(rows_all)
        else:
            shapes = {"ms_hist": (Mt, 3, 0, B), "ss_weight": (0, K, 3)}
            cat = {
                f: np.zeros(shapes.get(f, (0, K)), np.int32 if f == "ss_mat" else np.float32)
                for f in SSS_FIELDS
            }
            t_rows = np.zeros(0, np.int64)
        return Transport(
            pixels=jnp.asarray(np.concatenate(pix_all)),
            base=jnp.asarray(np.concatenate(base_all)),
            t_rows=jnp.asarray(t_rows.astype(np.int32)),
            r_nodes=jnp.asarray(tr.r_nodes, dtype=float),
            width=self.scene.camera.width,
            height=self.scene.camera.height,
            materials=tr.tmat_names,
            profile=self.scene.sss.profile,
            **{f: jnp.asarray(v) for f, v in cat.items()},
        )


def _take_block(out, i: int, valid: np.ndarray) -> dict:
    """Block `i` of a batch of `SSSBlock`s, keeping its `valid` rows."""
    d = {}
    for f in SSS_FIELDS:
        a = getattr(out, f)[i]
        d[f] = a[:, :, valid] if f == "ms_hist" else a[valid]
    return d


_CACHE: list[tuple[Scene, tuple, Renderer]] = []


def renderer_for(scene: Scene, devices=None) -> Renderer:
    """The compiled `Renderer` of `scene`, reused across calls (a few most recent scenes).

    Scenes are immutable, so the same object always means the same renderer; `with_settings`
    returns a new scene (and so a new renderer)."""
    devs = tuple(devices) if devices is not None else tuple(jax.devices())
    for sc, dv, r in _CACHE:
        if sc is scene and dv == devs:
            return r
    r = Renderer(scene, devs)
    _CACHE.insert(0, (scene, devs, r))
    del _CACHE[4:]
    return r


def trace_tiles(scene: Scene, key=None, *, progress: bool = False) -> Transport:
    """`trace` over the whole image, tile by tile (see `sssjax.trace.trace`)."""
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
    ordered = tuple(m[n] for n in r.tracer.tmat_names)
    leaves = jax.tree_util.tree_leaves(ordered)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        # under jax.grad / jacfwd / vmap: the differentiable path, shade(trace(scene)); the
        # media's eta bends the rays of the trace too, unless it is being differentiated
        etas = {
            n: float(md.eta)
            for n, md in zip(r.tracer.tmat_names, ordered, strict=True)
            if not isinstance(md.eta, jax.core.Tracer)
        }
        return shade_image(r.trace(key, progress, etas), ordered)
    return r.render(key, ordered, progress)
