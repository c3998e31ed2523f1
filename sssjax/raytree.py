"""The rays behind one pixel, recorded by the renderer's own tracing code.

`raytree(scene, pixel=(x, y))` re-runs, eagerly (not under `jit`), exactly the blocks of the
render that contain the pixel, with the render's own transport functions and random keys:
`trace_block` (camera rays, specular chains, shadow rays) for the pixel's tile, and, for the
two-phase diffusion transport, `trace_rows` (the dipole gather and single scattering) for
the packed block the renderer puts the pixel in. Those functions take a recorder argument
(`sssjax.transport.Recorder`; the renderer's compiled ones run with the no-op `NO_RECORD`),
whose hooks are called at the few places where rays are cast; this module's keeps the rows
of the chosen pixel. So the tree is the set of rays of the actual render, and the pixel's
radiance recomputed from the recorded run equals the rendered one (tested).

What is recorded (lengths in mm):

| kind | segment |
| --- | --- |
| `camera` | camera ray: camera to its first hit (or a light, or `far` along it on a miss) |
| `reflected` | a ray of the specular chain (mirror or Fresnel reflection), depth >= 1 |
| `shadow` / `shadow_blocked` | a shadow ray whose result the render uses: from a diffuse or first translucent vertex, a dipole sample point or a single-scattering exit point, to the light sample (lit) or to the occluder hit (blocked) |
| `ss_refracted` | single scattering: from `x_o` along the refracted ray to a scatter point |
| `ss_light` | single scattering: from the scatter point to where it leaves towards a light |
| `dipole` | per-pixel Monte Carlo strategies: from `x_o` to a dipole sample point |
| `walk` | volumetric transport: a free flight inside a medium (to a scattering point or the boundary) |
| `exit` | volumetric: the ray outside after a walk leaves its object (refracted out) |
| `bounce` | volumetric: the ray after a diffuse bounce |
| `connection` | volumetric: next-event estimation from a medium vertex, refracted at the boundary: vertex -> boundary point -> light (its last leg `shadow_blocked` when occluded) |

In the volumetric transport (`[sss] transport = "volumetric"`) the tree is the random walks
of the pixel's samples, event by event, with every next-event connection they tried (shadow
rays from diffuse vertices are `shadow` / `shadow_blocked`); `depth` is the event number.

Rays leave surfaces from a point offset by the tracer's `EPS` (1e-3 mm) along the normal, as
the tracer casts them, so a reflected or shadow ray starts up to 1e-3 mm from where its
parent ends. Dipole samples are also kept as points with their gather weight (the factor of
`R_d(r)` in the pixel, mean over RGB): for the cloud strategy the cloud points each of the
pixel's samples gathers from (the cloud itself is shared by all pixels; its own shadow rays
are not part of any pixel's tree, and points within the near-field radius have weight 0
because the near-field disc replaces them), for the Monte Carlo strategies the sampled
points; with beam lights also the beam's entry points each sample gathers from (weighted by
the power they carry in). Not recorded: the inside ray that measures an object's thickness
for single scattering, and the rays that build the shared cloud and beam points.

The first tree of a scene configuration is slow (each operation of the eager run is compiled
once: about 20-30 s of CPU time on 2 cores); later trees of the same scene take a fraction
of a second.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import MaterialKind
from ._files import check_outputs, save_figure, scene_inputs, write_text
from .scene import Scene, load_scene
from .transport import Recorder

__all__ = ["KINDS", "RayTree", "raytree", "plot_raytree", "raytree_files"]

KINDS = (
    "camera",
    "reflected",
    "shadow",
    "shadow_blocked",
    "ss_refracted",
    "ss_light",
    "dipole",
    "walk",
    "exit",
    "bounce",
    "connection",
)
(
    CAMERA,
    REFLECTED,
    SHADOW,
    SHADOW_BLOCKED,
    SS_REFRACTED,
    SS_LIGHT,
    DIPOLE,
    WALK,
    EXIT,
    BOUNCE,
    CONNECTION,
) = range(len(KINDS))

COLORS = {
    "camera": "#ffffff",
    "reflected": "#e41a1c",
    "shadow": "#4daf4a",
    "shadow_blocked": "#1e6b2c",
    "ss_refracted": "#1f78ff",
    "ss_light": "#74a9ff",
    "dipole": "#3050c0",
    "walk": "#ff9f1c",
    "exit": "#f781bf",
    "bounce": "#c08a3e",
    "connection": "#ffff66",
}
POINT_COLOR = "#00e5ff"
POINT_MIN_WEIGHT = 0.01  # points lighter than this fraction of the heaviest are not drawn


@dataclass(frozen=True, eq=False)
class RayTree:
    """Every ray the renderer casts for one pixel (NumPy arrays; lengths in mm).

    Segments (`N`): `origin`, `end` `(N, 3)`; `kind` `(N,)` codes into `KINDS`; `depth` the
    number of specular bounces before it (shadow and subsurface segments take the depth of
    the vertex they leave); `sample` the pixel sample (0..spp-1) it belongs to; `parent` the
    index of the segment it continues (-1 for camera rays); `miss` whether the ray left the
    scene (its `end` is then placed `far` mm along it).

    Dipole sample points (`K`): `points` `(K, 3)`, `point_weight` `(K,)` (the weight of
    `R_d(r)` in the pixel's radiance, mean over RGB), `point_sample` `(K,)`.

    `radiance` is the pixel's RGB radiance recomputed from the recorded run.
    """

    pixel: tuple[int, int]
    spp: int
    radiance: np.ndarray
    origin: np.ndarray
    end: np.ndarray
    kind: np.ndarray
    depth: np.ndarray
    sample: np.ndarray
    parent: np.ndarray
    miss: np.ndarray
    points: np.ndarray
    point_weight: np.ndarray
    point_sample: np.ndarray
    KINDS: ClassVar[tuple[str, ...]] = KINDS

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def counts(self) -> dict[str, int]:
        """Number of segments of each kind, by kind name (every kind present, maybe 0)."""
        return {name: int(np.sum(self.kind == i)) for i, name in enumerate(KINDS)}

    def of_kind(self, *names: str) -> np.ndarray:
        """Boolean mask of the segments whose kind is one of `names`."""
        bad = [n for n in names if n not in KINDS]
        if bad:
            raise ValueError(f"RayTree: unknown kind(s) {bad}; kinds: {', '.join(KINDS)}")
        return np.isin(self.kind, [KINDS.index(n) for n in names])

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": "sssjax.raytree/1",
            "units": "mm; radiance W mm^-2 sr^-1",
            "pixel": list(self.pixel),
            "spp": self.spp,
            "radiance": self.radiance.tolist(),
            "kinds": list(KINDS),
            "counts": self.counts(),
            "segments": {
                f: getattr(self, f).tolist()
                for f in ("origin", "end", "kind", "depth", "sample", "parent", "miss")
            },
            "points": {
                "position": self.points.tolist(),
                "weight": self.point_weight.tolist(),
                "sample": self.point_sample.tolist(),
            },
        }

    def to_json(self, path: str | Path | None = None) -> str:
        """The tree as JSON text (also written to `path` when given)."""
        text = json.dumps(self.to_dict())
        if path is not None:
            write_text(path, text)  # atomic
        return text

    @classmethod
    def from_json(cls, source: str | Path) -> RayTree:
        """A tree from `to_json` text or a file holding it."""
        text = str(source)
        if not text.lstrip().startswith("{"):
            text = Path(source).read_text()
        d = json.loads(text)
        if tuple(d.get("kinds", ())) != KINDS:
            raise ValueError(f"RayTree.from_json: kinds {d.get('kinds')} differ from {KINDS}")
        s, p = d["segments"], d["points"]
        return cls(
            pixel=tuple(d["pixel"]),
            spp=int(d["spp"]),
            radiance=np.asarray(d["radiance"], float),
            origin=np.asarray(s["origin"], float).reshape(-1, 3),
            end=np.asarray(s["end"], float).reshape(-1, 3),
            kind=np.asarray(s["kind"], np.int32),
            depth=np.asarray(s["depth"], np.int32),
            sample=np.asarray(s["sample"], np.int32),
            parent=np.asarray(s["parent"], np.int64),
            miss=np.asarray(s["miss"], bool),
            points=np.asarray(p["position"], float).reshape(-1, 3),
            point_weight=np.asarray(p["weight"], float),
            point_sample=np.asarray(p["sample"], np.int32),
        )


# --- the recorder -------------------------------------------------------------------------
@dataclass
class _Recorder(Recorder):
    """Collects the rays of the rows `rows` (of the block being traced) of one pixel.

    Called by the transport's hooks with the (eager) arrays of the whole block; keeps NumPy
    copies of the selected rows only.
    """

    active: ClassVar[bool] = True

    spp: int
    sss_on: bool
    far: float
    rows: np.ndarray | None = None
    cols: dict = field(default_factory=lambda: {f: [] for f in _SEG_FIELDS})
    pts: list = field(default_factory=list)
    n: int = 0
    _depth: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    _sample: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    _prev: np.ndarray | None = None  # (M,) segment of each row at the last chain depth
    _first: dict = field(default_factory=dict)  # sample -> segment ending at its x_o
    _ctx: np.ndarray | None = None  # parent segment of the next shadow rays, per leading index
    _ss: np.ndarray | None = None  # (M, n_ss) the ss_refracted segments
    _wprev: np.ndarray | None = None  # volumetric: each walker's last segment
    _wkind: np.ndarray | None = None  # volumetric: the kind of each walker's next flight outside

    def begin(self, rows: np.ndarray) -> None:
        """Start a block: record the rows where `rows` is True."""
        self.rows = np.asarray(rows, bool)
        self._prev = self._ctx = self._ss = None

    def _add(self, kind, origin, end, parent, depth=None, sample=None, miss=None) -> np.ndarray:
        parent = np.asarray(parent, np.int64).reshape(-1)
        m = parent.shape[0]
        if depth is None:
            depth, sample = self._depth[parent], self._sample[parent]
        vals = dict(
            origin=np.asarray(origin, float).reshape(m, 3),
            end=np.asarray(end, float).reshape(m, 3),
            kind=np.full(m, kind, np.int32),
            depth=np.broadcast_to(np.asarray(depth, np.int32), (m,)),
            sample=np.broadcast_to(np.asarray(sample, np.int32), (m,)),
            parent=parent,
            miss=np.zeros(m, bool) if miss is None else np.asarray(miss, bool).reshape(m),
        )
        for f, v in vals.items():
            self.cols[f].append(v)
        self._depth = np.concatenate([self._depth, vals["depth"]])
        self._sample = np.concatenate([self._sample, vals["sample"]])
        ids = np.arange(self.n, self.n + m)
        self.n += m
        return ids

    def _x_o(self, m: np.ndarray) -> np.ndarray:
        """The segment ending at the first translucent vertex of the samples of rows `m`."""
        return np.array([self._first.get(int(i) % self.spp, -1) for i in m], np.int64)

    # -- hooks called by the transport ---------------------------------------------------------
    def chain(self, depth, o, d, x, t_light, alive, hit_light, hit, kind, first) -> None:
        """Rays of one depth of the specular chains (`chain_block`)."""
        o, d, x, t_light = (np.asarray(a, float) for a in (o, d, x, t_light))
        alive, hit_light, hit, first = (np.asarray(a, bool) for a in (alive, hit_light, hit, first))
        kind = np.asarray(kind)
        M = o.shape[0]
        sel = self.rows & alive
        m = np.flatnonzero(sel)
        tl = np.where(np.isfinite(t_light), t_light, 0.0)[:, None]
        end = np.where(hit_light[:, None], o + tl * d, np.where(hit[:, None], x, o + self.far * d))
        parent = self._prev[m] if depth > 0 else np.full(len(m), -1)
        ids = self._add(
            CAMERA if depth == 0 else REFLECTED,
            o[m],
            end[m],
            parent,
            depth,
            m % self.spp,
            ~(hit | hit_light)[m],
        )
        self._prev = np.full(M, -1, np.int64)
        self._prev[m] = ids
        # shadow rays whose result the render uses: at diffuse vertices, and at the first
        # translucent vertex of a sample (its E(x_o)) when subsurface scattering is on
        first = first & self.sss_on
        used = sel & hit & ((kind == MaterialKind.DIFFUSE) | first)
        self._ctx = np.where(used, self._prev, -1)
        for i in np.flatnonzero(sel & hit & first):
            self._first[int(i) % self.spp] = int(self._prev[i])

    def shadow(self, o, d, t, t_max) -> None:
        """Shadow rays (`SceneArrays.occluded`): attributed to the current context."""
        if self._ctx is None:
            return
        o, d = np.broadcast_arrays(np.asarray(o, float), np.asarray(d, float))
        t = np.asarray(t, float)
        t_max = np.broadcast_to(np.asarray(t_max, float), t.shape)
        ctx = self._ctx
        if o.shape[: ctx.ndim] != ctx.shape:
            raise RuntimeError(
                f"raytree: shadow rays of shape {o.shape} do not match the recording context "
                f"{ctx.shape} (a tracer hook is missing)"
            )
        C = ctx.size
        o, d = o.reshape(C, -1, 3), d.reshape(C, -1, 3)
        t, t_max = t.reshape(C, -1), t_max.reshape(C, -1)
        parent = np.broadcast_to(ctx.reshape(C, 1), t.shape)
        sel = parent >= 0
        if not sel.any():
            return
        blocked = t < t_max
        tt = np.where(blocked, t, t_max)
        end = o + tt[..., None] * d
        for b, kind in ((False, SHADOW), (True, SHADOW_BLOCKED)):
            s = sel & (blocked == b)
            if s.any():
                self._add(kind, o[s], end[s], parent[s])

    def points(self, p, w, have) -> None:
        """Dipole sample points and their gather weights `w (M, n, 3)`; `p` is `(M, n, 3)` or
        `(P or 1, spp, n, 3)` (the cloud subset of each sample)."""
        have = np.asarray(have, bool)
        m = np.flatnonzero(self.rows & have)
        p = np.asarray(p)
        if p.ndim == 4:
            p = p[(m // self.spp) if p.shape[0] > 1 else 0, m % self.spp]
        else:
            p = p[m]
        w = np.asarray(w)[m].astype(float).mean(axis=-1)
        n = p.shape[1]
        self.pts.append((p.reshape(-1, 3).astype(float), w.reshape(-1), np.repeat(m % self.spp, n)))

    def dipole(self, xo, p, have) -> None:
        """Per-pixel Monte Carlo dipole samples: segments `x_o -> p` (`p (M, K, 3)`), which
        parent the shadow rays cast from the sample points."""
        xo, p = np.asarray(xo, float), np.asarray(p, float)
        M, K = p.shape[:2]
        m = np.flatnonzero(self.rows & np.asarray(have, bool))
        parent = np.repeat(self._x_o(m), K)
        ids = self._add(DIPOLE, np.repeat(xo[m], K, axis=0), p[m], parent)
        self._ctx = np.full((M, K), -1, np.int64)
        self._ctx[m] = ids.reshape(len(m), K)

    def ss_paths(self, xo, xs, have) -> None:
        """Single scattering: `x_o -> ` each scatter point `xs (M, n_ss, 3)`."""
        xo, xs = np.asarray(xo, float), np.asarray(xs, float)
        M, K = xs.shape[:2]
        m = np.flatnonzero(self.rows & np.asarray(have, bool))
        ids = self._add(
            SS_REFRACTED, np.repeat(xo[m], K, axis=0), xs[m], np.repeat(self._x_o(m), K)
        )
        self._ss = np.full((M, K), -1, np.int64)
        self._ss[m] = ids.reshape(len(m), K)
        self._ctx = None

    def ss_exit(self, xs, xi) -> None:
        """Single scattering towards one light: scatter point -> exit point; the shadow ray
        cast from the exit point next is its child."""
        xs, xi = np.asarray(xs, float), np.asarray(xi, float)
        sel = self._ss >= 0
        ids = self._add(SS_LIGHT, xs[sel], xi[sel], self._ss[sel])
        self._ctx = np.full(self._ss.shape, -1, np.int64)
        self._ctx[sel] = ids

    def walk(self, event: int, rays: dict) -> None:
        """One event of the volumetric walks (`Recorder.walk`): the flight as a `camera`,
        `reflected`, `exit`, `bounce` or `walk` segment (by what came before it), and the
        next-event connections tried from its end."""
        alive = rays["alive"]
        W = alive.shape[0]
        if event == 0:
            self._wprev = np.full(W, -1, np.int64)
            self._wkind = np.full(W, CAMERA, np.int32)
        m = np.flatnonzero(alive)
        if not len(m):
            return
        code = rays["code"]
        kind = np.where(rays["inside"][m], WALK, self._wkind[m])
        miss = code[m] == _EVENT["miss"]
        end = np.where(miss[:, None], rays["o"][m] + self.far * rays["d"][m], rays["end"][m])
        ids = np.zeros(len(m), np.int64)
        for k in np.unique(kind):
            s = kind == k
            ids[s] = self._add(
                int(k),
                rays["o"][m][s],
                end[s],
                self._wprev[m][s],
                event,
                rays["sample"][m][s],
                miss[s],
            )
        self._wprev[m] = ids
        # what the next flight outside is drawn as
        nxt = {
            "mirror": REFLECTED,
            "reflect_outside": REFLECTED,
            "exit": EXIT,
            "diffuse": BOUNCE,
        }
        for name, k in nxt.items():
            self._wkind[m[code[m] == _EVENT[name]]] = k
        for key, legs in (("nee_m", True), ("nee_d", False)):
            c = rays[key]
            t = np.flatnonzero(c["tried"] & alive)
            if not len(t):
                continue
            parent = self._wprev[t]
            depth, sample = event, rays["sample"][t]
            vis = c["vis"][t]
            if legs:  # vertex -> boundary point, then boundary point -> light
                first = self._add(CONNECTION, c["x"][t], c["b"][t], parent, depth, sample)
                parent = first
                start = c["b"][t]
            else:
                start = c["x"][t]
            for v, k in ((True, CONNECTION if legs else SHADOW), (False, SHADOW_BLOCKED)):
                s = vis == v
                if s.any():
                    self._add(k, start[s], c["y"][t][s], parent[s], depth, sample[s])

    def tree(self, pixel, radiance) -> RayTree:
        cat = {
            f: np.concatenate(v) if v else np.zeros((0, 3) if f in ("origin", "end") else 0)
            for f, v in self.cols.items()
        }
        if self.pts:
            pts, w, s = (np.concatenate(a) for a in zip(*self.pts, strict=True))
        else:
            pts, w, s = np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32)
        return RayTree(
            pixel=tuple(int(v) for v in pixel),
            spp=self.spp,
            radiance=np.asarray(radiance, float),
            origin=cat["origin"].astype(float),
            end=cat["end"].astype(float),
            kind=cat["kind"].astype(np.int32),
            depth=cat["depth"].astype(np.int32),
            sample=cat["sample"].astype(np.int32),
            parent=cat["parent"].astype(np.int64),
            miss=cat["miss"].astype(bool),
            points=pts,
            point_weight=w,
            point_sample=s.astype(np.int32),
        )


_SEG_FIELDS = ("origin", "end", "kind", "depth", "sample", "parent", "miss")
_EVENT = {
    name: i
    for i, name in enumerate(
        (
            "scatter",
            "reflect_inside",
            "exit",
            "light",
            "miss",
            "diffuse",
            "mirror",
            "reflect_outside",
            "enter",
            "through",
            "cut",
        )
    )
}  # sssjax.transport.volumetric.EVENT (not imported: the module loads on first use)


@jax.jit
def _shade(terms, media):
    """The shading of recorded terms (no rays are cast there), compiled as the renderer's."""
    return terms.shade(media)


def scene_extent(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box around the shapes, the lights and the camera (mm)."""
    pts = [np.asarray(scene.camera.origin, float)]
    for s in scene.shapes:
        pts.extend(np.asarray(b, float) for b in s.shape.bounds())
    for light in scene.lights:
        for a in ("corner", "position"):
            if hasattr(light, a):
                pts.append(np.asarray(getattr(light, a), float))
        if hasattr(light, "edge_u"):
            c = np.asarray(light.corner, float)
            pts.append(c + np.asarray(light.edge_u, float) + np.asarray(light.edge_v, float))
    pts = np.stack(pts)
    return pts.min(axis=0), pts.max(axis=0)


def raytree(
    scene: Scene | str | Path, pixel: tuple[int, int], key=None, *, renderer=None
) -> RayTree:
    """Record every ray the renderer casts for one pixel.

    **Arguments:**

    - `scene`: a `Scene` (or a scene file path).
    - `pixel`: `(x, y)`, x to the right, y down, from 0.
    - `key`: the render's `jax.random` key or integer seed (default: the scene's seed); the
      tree is the rays of `render(scene, key)` for that pixel.
    - `renderer`: the `Renderer` to follow (default: the cached one of `scene`).

    **Returns:** a `RayTree`. Its `radiance` equals `render(scene, key)[y, x]` up to float
    rounding (eager versus compiled arithmetic).
    """
    from .render import as_key, renderer_for

    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    cam = scene.camera
    try:
        x, y = (int(v) for v in pixel)
    except (TypeError, ValueError):
        raise ValueError(f"raytree: pixel must be two integers (x, y), got {pixel!r}") from None
    if not (0 <= x < cam.width and 0 <= y < cam.height):
        raise ValueError(
            f"raytree: pixel ({x}, {y}) is outside the {cam.width}x{cam.height} image "
            f"(x in 0..{cam.width - 1}, y in 0..{cam.height - 1})"
        )
    r = renderer if renderer is not None else renderer_for(scene)
    key = as_key(key, scene)
    pid = y * cam.width + x
    tm, arrays = r.transport, r.arrays
    packs = tm.two_phase and tm.media_dependent
    state = r.image_state(key, arrays)

    # The compiled renderer's tiles, chunk by chunk as `Renderer.render` does, up to the
    # pixel's chunk: this fixes the packed second-phase block (rows, key) of the pixel.
    counter = [0]
    found = None
    for pix, _base, needs, rows in r.chunks(key, None, arrays, state):
        if packs:
            for rr, valid, blk, _valid, keys in r.packed(key, needs, rows, counter):
                at = np.argwhere(valid & (pix[rr] == pid))
                if found is None and len(at):
                    i, j = (int(v) for v in at[0])
                    one = jax.tree_util.tree_map(lambda v, i=i: jnp.asarray(v[i]), blk)
                    found = (one, jnp.asarray(valid[i]), keys[i], j)
        if np.any(pix == pid):
            break

    lo, hi = scene_extent(scene)
    S = scene.render.spp
    rec = _Recorder(spp=S, sss_on=tm.media_dependent, far=float(np.linalg.norm(hi - lo)) + 1.0)
    media = tuple(scene.media()[n] for n in arrays.materials)

    # the pixel's tile, with the tile's key (`Renderer.chunks`), eagerly with the recorder
    b = pid // r.block
    start = min(b, r.n_blocks - 1) * r.block
    pix_blk = np.minimum(start + np.arange(r.block), r.n_pixels - 1).astype(np.int32)
    pos = pid - start
    k_tile = jax.random.fold_in(jax.random.fold_in(key, 1), b)
    rec.begin(np.arange(r.block * S) // S == pos)
    base, needs, rows = tm.trace_block(arrays, state, jnp.asarray(pix_blk), k_tile, rec)
    L = np.asarray(base)[pos].astype(float)
    if tm.media_dependent and not tm.two_phase and bool(needs[pos]):
        L = L + np.asarray(_shade(rows.rows(jnp.asarray([pos])), media))[0]

    # a two-phase transport: the pixel's packed block, with its key (`Renderer.packed`)
    if found is not None:
        blk, valid, k_blk, j = found
        rec.begin(np.arange(r.block * S) // S == j)
        terms = tm.trace_rows(arrays, state, blk, valid, k_blk, rec)
        L = L + np.asarray(_shade(terms, media))[j]
    return rec.tree((x, y), L)


# --- the picture --------------------------------------------------------------------------
def _clip_front(a: np.ndarray, b: np.ndarray, z_a, z_b, near: float):
    """Clip segments `a -> b` to camera depth `z >= near`; returns the kept parts and mask."""
    keep = (z_a >= near) | (z_b >= near)
    da = np.where(z_a < near, (near - z_a) / np.where(z_b != z_a, z_b - z_a, 1.0), 0.0)
    db = np.where(z_b < near, (near - z_b) / np.where(z_a != z_b, z_a - z_b, 1.0), 0.0)
    a2 = a + da[:, None] * (b - a)
    b2 = b + db[:, None] * (a - b)
    return a2, b2, keep


def _style(kcode: int) -> dict:
    if kcode == SHADOW_BLOCKED:
        return dict(linewidths=0.9, alpha=0.9, linestyles=(0, (3, 2)), zorder=2)
    return dict(linewidths=1.1 if kcode in (SS_REFRACTED, SS_LIGHT) else 0.9, alpha=0.9, zorder=2)


def _heavy_points(tree: RayTree):
    """The dipole points drawn (area ~ weight; those under 1% of the heaviest are left out)
    and their marker sizes."""
    wmax = float(tree.point_weight.max()) if tree.point_weight.size else 0.0
    heavy = tree.point_weight >= POINT_MIN_WEIGHT * wmax if wmax > 0 else tree.point_weight > 0
    sizes = 0.3 + 12.0 * tree.point_weight[heavy] / (wmax if wmax > 0 else 1.0)
    return tree.points[heavy], sizes


def _camera_view(ax0, tree: RayTree, scene: Scene, image, note: str, pts, sizes) -> None:
    """The segments and points over the image, seen by the scene camera."""
    from matplotlib.collections import LineCollection

    from .camera import project
    from .imageio import srgb_encode, tonemap
    from .plots import _pyplot

    plt = _pyplot()
    cam = scene.camera
    W, H = cam.width, cam.height
    fwd = np.asarray(cam.basis()[0], float)
    org = np.asarray(cam.origin, float)
    lo, hi = scene_extent(scene)
    scale = float(np.linalg.norm(hi - lo))
    if image is not None:
        ax0.imshow(srgb_encode(tonemap(np.asarray(image))), extent=(0, W, H, 0))
    z_o = (tree.origin - org) @ fwd
    z_e = (tree.end - org) @ fwd
    if cam.projection == "orthographic":
        a, b, keep = tree.origin, tree.end, np.ones(len(tree), bool)
    else:
        a, b, keep = _clip_front(tree.origin, tree.end, z_o, z_e, 1e-4 * scale)
    pa = np.asarray(project(cam, jnp.asarray(a)), float) if len(tree) else np.zeros((0, 2))
    pb = np.asarray(project(cam, jnp.asarray(b)), float) if len(tree) else np.zeros((0, 2))
    order = [CAMERA, DIPOLE, SS_REFRACTED, SS_LIGHT, WALK, CONNECTION, SHADOW_BLOCKED, SHADOW]
    order += [REFLECTED, EXIT, BOUNCE]
    for kcode in order:
        s = keep & (tree.kind == kcode)
        if s.any():
            segs = np.stack([pa[s], pb[s]], axis=1)
            ax0.add_collection(LineCollection(segs, colors=COLORS[KINDS[kcode]], **_style(kcode)))
    if len(pts):
        zp = (pts - org) @ fwd
        ok = zp > 0 if cam.projection != "orthographic" else np.ones(len(zp), bool)
        pp = np.asarray(project(cam, jnp.asarray(pts)), float)
        ax0.scatter(*pp[ok].T, s=sizes[ok], c=POINT_COLOR, alpha=0.35, linewidths=0, zorder=1)
    x, y = tree.pixel
    ax0.add_patch(plt.Rectangle((x, y), 1, 1, fill=False, ec="#ffff00", lw=1.2))
    ax0.set_xlim(0, W)
    ax0.set_ylim(H, 0)
    ax0.set_aspect("equal")
    ax0.set_title(f"camera view{(' — ' + note) if note else ''}", color="#dddddd", fontsize=10)


def _legend_handles(tree: RayTree, counts: dict, pts) -> list:
    """One legend entry per kind present, and the dipole points."""
    from matplotlib.lines import Line2D

    handles = [
        Line2D(
            [],
            [],
            color=COLORS[k],
            lw=2,
            ls="--" if k == "shadow_blocked" else "-",
            label=f"{k.replace('_', ' ')} ({counts[k]})",
        )
        for k in KINDS
        if counts[k]
    ]
    if tree.points.size:
        handles.append(
            Line2D(
                [],
                [],
                ls="",
                marker="o",
                color=POINT_COLOR,
                label=f"dipole samples ({len(tree.points)}; {len(pts)} drawn: weight >= 1% "
                "of the heaviest, area ~ weight)",
            )
        )
    return handles


def plot_raytree(
    tree: RayTree,
    scene: Scene,
    path: str | Path,
    *,
    image: np.ndarray | None = None,
    note: str = "",
    dpi: int = 110,
) -> Path:
    """Draw `tree` over `image` (linear RGB seen by the scene camera, any resolution) and in a
    side view (orthographic, looking along the camera's right axis), coloured by kind.

    **Returns:** the path of the PNG written.
    """
    from matplotlib.collections import LineCollection

    from .plots import _pyplot

    plt = _pyplot()
    cam = scene.camera
    fwd, right, up = (np.asarray(v, float) for v in cam.basis())
    org = np.asarray(cam.origin, float)
    counts = tree.counts()

    close_up = bool(np.any(tree.of_kind("ss_refracted", "ss_light", "dipole", "walk")))
    if close_up:
        fig, (ax0, ax1, ax2) = plt.subplots(
            1, 3, figsize=(19, 6.6), facecolor="#111111", width_ratios=(1.35, 1, 1)
        )
    else:
        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(14, 6.6), facecolor="#111111")
        ax2 = None
    for ax in (ax0, ax1, ax2) if close_up else (ax0, ax1):
        ax.set_facecolor("#1b1b1b")
        ax.tick_params(colors="#bbbbbb", labelsize=8)
        for s in ax.spines.values():
            s.set_color("#555555")

    pts, sizes = _heavy_points(tree)
    _camera_view(ax0, tree, scene, image, note, pts, sizes)
    order = [CAMERA, DIPOLE, SS_REFRACTED, SS_LIGHT, WALK, CONNECTION, SHADOW_BLOCKED, SHADOW]
    order += [REFLECTED, EXIT, BOUNCE]

    # -- side views: orthographic along the camera's right axis ---------------------------
    def side(p):
        v = np.asarray(p, float) - org
        return np.stack([v @ fwd, v @ up], axis=-1)

    meshes = []
    for s in scene.shapes:
        v, tris = s.shape.tessellate(24)
        e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        meshes.append(side(v)[np.unique(np.sort(e, axis=1), axis=0)])
    so, se = side(tree.origin), side(tree.end)

    def draw_side(ax, lo2, hi2, title):
        for m in meshes:
            ax.add_collection(
                LineCollection(m, colors="#8a8a8a", linewidths=0.3, alpha=0.35, zorder=0)
            )
        for light in scene.lights:
            if hasattr(light, "edge_u"):
                c = np.asarray(light.corner, float)
                eu, ev = np.asarray(light.edge_u, float), np.asarray(light.edge_v, float)
                q = side(np.stack([c, c + eu, c + eu + ev, c + ev, c]))
                ax.plot(*q.T, color="#ffd700", lw=1.5)
            elif hasattr(light, "position"):
                q = side(np.asarray(light.position, float)[None])[0]
                ax.plot(*q, marker="*", color="#ffd700", ms=10)
        ax.plot(0, 0, marker=">", color="#ffffff", ms=9)
        for kcode in order:
            s = tree.kind == kcode
            if s.any():
                segs = np.stack([so[s], se[s]], axis=1)
                ax.add_collection(
                    LineCollection(segs, colors=COLORS[KINDS[kcode]], **_style(kcode))
                )
        if len(pts):
            ax.scatter(*side(pts).T, s=sizes, c=POINT_COLOR, alpha=0.35, linewidths=0, zorder=1)
        pad = 0.08 * max(float(np.max(hi2 - lo2)), 1e-3)
        ax.set_xlim(lo2[0] - pad, hi2[0] + pad)
        ax.set_ylim(lo2[1] - pad, hi2[1] + pad)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("along the camera axis [mm]", color="#bbbbbb", fontsize=9)
        ax.set_ylabel("camera up [mm]", color="#bbbbbb", fontsize=9)
        ax.set_title(title, color="#dddddd", fontsize=10)

    # the whole tree: its hit points (not the ends of escaped rays), the camera and points
    fin = np.concatenate([so, se[~tree.miss], side(tree.points), np.zeros((1, 2))])
    draw_side(ax1, fin.min(axis=0), fin.max(axis=0), "side view (orthographic, camera at left)")
    if ax2 is not None:
        sub = tree.of_kind("ss_refracted", "ss_light", "dipole", "walk")
        c = np.concatenate([so[sub], se[sub]]).mean(axis=0)
        ends = np.concatenate([so[sub], se[sub]])
        half = max(1.2 * float(np.max(np.abs(ends - c))), 0.5)
        draw_side(ax2, c - half, c + half, "close-up of the subsurface paths (side view)")

    handles = _legend_handles(tree, counts, pts)
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=min(len(handles), 4) or 1,
        fontsize=9,
        facecolor="#222222",
        edgecolor="#555555",
        labelcolor="#eeeeee",
    )
    rad = ", ".join(f"{v:.4g}" for v in tree.radiance)
    x, y = tree.pixel
    fig.suptitle(
        f"rays behind pixel ({x}, {y}), {tree.spp} spp: {len(tree)} segments; radiance ({rad})",
        color="#eeeeee",
        fontsize=11,
    )
    fig.tight_layout(rect=(0, 0.11, 1, 0.95))
    try:
        return save_figure(fig, path, dpi=dpi, facecolor=fig.get_facecolor())
    finally:
        plt.close(fig)


def raytree_files(
    scene_path: str | Path,
    pixel: tuple[int, int],
    *,
    json_path: str | Path | None = None,
    png_path: str | Path | None = None,
    seed: int | None = None,
    image_path: str | Path | None = None,
    force: bool = False,
    backdrop_size: int = 160,
    log=print,
) -> tuple[RayTree, Path, Path]:
    """The `sssjax raytree` command: record the tree, write it as JSON and as a picture.

    Without `image_path` the backdrop is a quick render of the scene at most `backdrop_size`
    pixels wide or high and at most 4 spp (stated in the picture). Existing outputs are not
    overwritten unless `force`; the scene and the backdrop image never are.

    **Returns:** `(tree, json_path, png_path)`.
    """
    from .imageio import read_image
    from .render import render

    scene = load_scene(scene_path)
    x, y = pixel
    stem = Path(scene_path).stem
    json_path = Path(json_path or Path("out") / f"{stem}_raytree_{x}_{y}.json")
    png_path = Path(png_path or Path("out") / f"{stem}_raytree_{x}_{y}.png")
    inputs = [Path(scene_path)] + ([Path(image_path)] if image_path else [])
    inputs += scene_inputs(scene)
    check_outputs([json_path, png_path], force=force, inputs=inputs)
    if image_path is not None and not Path(image_path).is_file():
        raise FileNotFoundError(f"image not found: {image_path}")  # before the tracing
    if png_path.suffix.lower() != ".png":
        raise ValueError(f"--png {png_path}: expected a .png file")
    seed = scene.render.seed if seed is None else seed
    tree = raytree(scene, (x, y), seed)
    c = tree.counts()
    log(
        f"pixel ({x}, {y}): {len(tree)} segments ("
        + ", ".join(f"{k} {v}" for k, v in c.items() if v)
        + f"), {len(tree.points)} dipole points; radiance "
        + " ".join(f"{v:.5g}" for v in tree.radiance)
    )
    if image_path is not None:
        image = read_image(image_path)
        note = f"backdrop {Path(image_path).name}"
    else:
        cam = scene.camera
        f = min(1.0, backdrop_size / max(cam.width, cam.height))
        w, h = max(1, round(cam.width * f)), max(1, round(cam.height * f))
        spp = min(scene.render.spp, 4)
        log(f"rendering a {w}x{h} backdrop at {spp} spp (pass --image to use your own render)")
        same = (w, h, spp) == (cam.width, cam.height, scene.render.spp)
        # the scene itself when nothing changes: its renderer is compiled already
        image = render(scene if same else scene.with_settings(width=w, height=h, spp=spp), seed)
        note = "backdrop: the render" if same else f"backdrop: quick render {w}x{h}, {spp} spp"
    tree.to_json(json_path)
    plot_raytree(tree, scene, png_path, image=image, note=note)
    return tree, json_path, png_path
