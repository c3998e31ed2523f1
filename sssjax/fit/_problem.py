"""A fit problem (`FitProblem`): the target, the free parameters and what the solver's
coordinates mean (`Layout`), the traced data (`TraceData`, one trace per light group) and
the residuals of the shading (`Args`, `model`, `residual_fn`).

The data reach the shading only through the transport's terms protocol
(`Terms.rows`, `Terms.mean`, `Terms.prepare`, `Prepared.shade`): the fit does not know which
transport traced them. Coefficients in mm^-1.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.ndimage import binary_dilation

from .. import params as _params
from ..media import Medium
from ..params import Enters, Parameter, ParameterError
from ..render import as_key, renderer_for
from ..scene import Scene
from ..transport import TRANSPORTS
from ._options import LOSSES, WEIGHTINGS, FitOptions
from ._result import FitError

__all__ = [
    "FitProblem",
    "Layout",
    "Args",
    "TraceData",
    "trace_data",
    "residual_args",
    "model",
    "residual_fn",
    "light_groups",
    "highlights",
    "load_target",
    "HIGHLIGHT_LEVEL",
    "ETA_RANGE",
]

ETA_RANGE = (1.0, 2.5)  # the refractive indices a fit of eta searches (exclusive of 1)
HIGHLIGHT_LEVEL = 4.0  # a highlight is this many times the translucent pixels' median
_CH = "RGB"


def load_target(target, shape: tuple[int, int]) -> np.ndarray:
    """`target` (an `(H, W, 3)` array or an image path) checked against the camera's size."""
    if isinstance(target, str | Path):
        from ..imageio import read_image

        path = Path(target)
        if not path.exists():
            raise FitError(f"target image not found: {path}")
        arr = read_image(path)
        where = str(path)
    else:
        arr = np.asarray(target, dtype=np.float64)
        where = "target"
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise FitError(f"{where}: expected an (H, W, 3) RGB image, got shape {arr.shape}")
    if arr.shape[:2] != shape:
        raise FitError(
            f"{where}: size {arr.shape[1]}x{arr.shape[0]} does not match the "
            f"scene's camera {shape[1]}x{shape[0]}"
        )
    bad = ~np.isfinite(arr)
    if bad.any():
        raise FitError(f"{where}: {int(bad.any(axis=2).sum())} pixels are NaN or inf")
    if not np.any(arr > 0):
        raise FitError(f"{where}: the target is all black")
    return arr


def light_groups(n_lights: int, free_lights: Sequence[int]) -> list[np.ndarray | None]:
    """Per-light emission factors of traces whose transports add up to the scene's: one per
    free light (only that light emitting), then one with the other lights (absent when
    every light is free); `[None]` (the scene as it is) when no light is free. Every light
    stays in the scene, dark or not, so rays, samples and random numbers are the scene's and
    each trace is exactly its lights' share (the volumetric transport's in expectation: its
    next-event estimation picks a light by its power, gain included, so the groups' walks
    differ)."""
    if not free_lights:
        return [None]
    rest = [i for i in range(n_lights) if i not in free_lights]
    groups = [[i] for i in free_lights] + ([rest] if rest else [])
    return [np.isin(np.arange(n_lights), g).astype(np.float64) for g in groups]


def highlights(pix, base, tgt, shape) -> np.ndarray:
    """`(H, W)` highlight pixels: a light's mirror reflection on the translucent surface,
    where the trace's medium-independent radiance `base` (summed over light groups) is
    both more than half the target's and more than `HIGHLIGHT_LEVEL` times the translucent
    pixels' median, grown by one pixel. A highlight's jittered edge differs between traces
    by hundreds of times the subsurface signal, so a handful of such pixels would otherwise
    decide the loss; a dim reflection (of the floor, say) is kept."""
    lum = np.array([0.2126, 0.7152, 0.0722])
    b, t = base.sum(0) @ lum, tgt @ lum
    level = HIGHLIGHT_LEVEL * max(float(np.median(np.abs(t))), 1e-30)
    hl = np.zeros(shape[0] * shape[1], dtype=bool)
    hl[pix[(b > 0.5 * np.maximum(t, 0.0)) & (b > level)]] = True
    return binary_dilation(hl.reshape(shape), structure=np.ones((3, 3), dtype=bool))


@dataclasses.dataclass
class TraceData:
    """What a fit keeps of one trace (one transport per light group): the terms of the
    fitted pixels (`Terms` per group), their target values `(N, 3)` and medium-independent
    radiance `base (G, N, 3)`; the mask used, the fitted pixels `pix` and every pixel with
    terms `all_pix` (flat image indices)."""

    terms: list
    target: np.ndarray
    base: np.ndarray
    materials: tuple
    mask: np.ndarray
    pix: np.ndarray
    all_pix: np.ndarray

    def left_out(self, shape) -> np.ndarray:
        """`(H, W)` the pixels with terms that the mask left out."""
        out = np.zeros(shape[0] * shape[1], dtype=bool)
        out[self.all_pix] = True
        return out.reshape(shape) & ~self.mask


def trace_data(
    renderer, gains, key, tgt, mask, progress: bool, etas=None, proposal=None, fixed=None
) -> TraceData:
    """Trace once per light group (`gains`, from `light_groups`; `etas`: refractive indices
    by material; `proposal`: the media a re-weighting transport samples with, by material)
    and keep what the fit needs. `mask=None` fits every pixel with terms but the
    highlights (`highlights`); `TraceData.mask` is the mask used. `fixed` (flat pixel
    indices, within `mask`): the pixels an earlier trace fitted, which this one fits too,
    with zero terms where none of its samples reached a medium (one-phase transports, the
    volumetric one: `Renderer.trace`'s `keep`). Why: a pixel on an object's silhouette, or
    on the floor beside it, has terms only when one of its samples happens to reach the
    medium, and fitting it only then fits a model conditioned on its own noise (at 8 spp a
    pixel a sixteenth covered has terms in 40 % of traces, each holding at least one
    sample's worth of the object: 2.5 times its share), where the target holds its
    unconditional mean; and the rounds' common pixels (`_aligned`) shrank to 55 % of one
    trace's on a 64 x 64 cylinder over 10 rounds (measured 2026-12-07)."""
    keep = None
    if fixed is not None:
        keep = np.zeros(tgt.shape[0] * tgt.shape[1], dtype=bool)
        keep[np.asarray(fixed)] = True
    transports = [renderer.trace(key, progress, etas, g, proposal, keep) for g in gains]
    sets = [np.asarray(t.translucent_pixels()) for t in transports]
    if keep is None and any(not np.array_equal(np.sort(p), np.sort(sets[0])) for p in sets[1:]):
        # a walk that reaches only one group's light has terms in that group alone: trace
        # them again keeping the union, so that every group has rows for the same pixels
        # (once: a later trace keeps the fitted pixels in every group already)
        keep = np.zeros(tgt.shape[0] * tgt.shape[1], dtype=bool)
        keep[np.concatenate(sets)] = True
        transports = [renderer.trace(key, progress, etas, g, proposal, keep) for g in gains]
    transport = transports[0]
    pix = np.asarray(transport.translucent_pixels())
    rows = np.asarray(transport.t_rows)
    if mask is None and len(pix):
        base_all = np.stack([np.asarray(t.base)[rows] for t in transports])
        mask = ~highlights(pix, base_all, tgt.reshape(-1, 3)[pix], tgt.shape[:2])
        if not mask.reshape(-1)[pix].any():  # nothing but highlight: fit it all
            mask = np.ones(tgt.shape[:2], dtype=bool)
    if keep is not None:
        rows_sel = np.flatnonzero(keep[pix])
    elif mask is not None:
        rows_sel = np.flatnonzero(mask.reshape(-1)[pix])
        if len(rows_sel) == 0:
            raise FitError("the mask selects no pixel that sees a translucent object")
    else:
        if len(pix) == 0:
            raise FitError("no pixel sees a translucent object: nothing to fit")
        rows_sel = np.arange(len(pix))
    return TraceData(
        terms=[t.terms.rows(_rows_of(t, pix[rows_sel])) for t in transports],
        target=tgt.reshape(-1, 3)[pix[rows_sel]],
        base=np.stack([np.asarray(t.base)[rows[rows_sel]] for t in transports]),
        materials=transport.materials,
        mask=mask,
        pix=pix[rows_sel],
        all_pix=pix,
    )


def _rows_of(transport, pixels: np.ndarray):
    """The rows of `transport`'s terms that hold `pixels` (flat indices), in their order:
    light groups' transports may list their pixels apart."""
    own = np.asarray(transport.translucent_pixels())
    order = np.argsort(own)
    i = order[np.clip(np.searchsorted(own[order], pixels), 0, max(own.size - 1, 0))]
    if own.size == 0 or not np.array_equal(own[i], pixels):
        raise RuntimeError("a light group's trace lacks terms for fitted pixels")
    return jnp.asarray(i)


# The residual and solver functions are cached per parameter layout, and the data travel as
# `Args`, so a second fit of the same layout reuses the compiled step.
@dataclasses.dataclass(frozen=True)
class Layout:
    """What the solver's coordinates mean: 3 per free `(material, field)` (log, or atanh for
    `g`), then the log intensity factor of each free light, then the log exposure."""

    free: tuple
    order: tuple  # the transport's translucent materials
    exposure: bool
    n_lights: int

    def media(self, y, media0) -> tuple:
        """Media with the free coefficients set from `y` (its first `3 len(free)` entries:
        log of the coefficients, atanh of `g`)."""
        logs = {k: y[3 * i : 3 * i + 3] for i, k in enumerate(self.free)}
        out = []
        for mat, m in zip(self.order, media0, strict=True):
            g = jnp.tanh(logs[(mat, "g")]) if (mat, "g") in logs else m.g
            sa = jnp.exp(logs[(mat, "sigma_a")]) if (mat, "sigma_a") in logs else m.sigma_a
            if (mat, "sigmap_s") in logs:
                ss = jnp.exp(logs[(mat, "sigmap_s")]) / (1.0 - g)
            elif (mat, "sigma_s") in logs:
                ss = jnp.exp(logs[(mat, "sigma_s")])
            else:
                ss = m.sigma_s
            out.append(Medium(sa, ss, g, m.eta))
        return tuple(out)


class Args(eqx.Module):
    """The residual functions' data: prepared terms and medium-independent radiance per
    light group and the target, in units of the target's mean level `scale`; the media held
    fixed; the robust-loss scale and the per-pixel weights."""

    terms: tuple
    target: Float[Array, "N 3"]
    media0: tuple
    scale: Float[Array, ""]
    loss_scale: Float[Array, ""]
    base: Float[Array, "G N 3"]
    weights: Float[Array, "N 3"]
    # re-weighting transports: each group's terms in two independent halves (`Prepared.halves`)
    halves: tuple | None = None


def row_pixels(data: list[TraceData]) -> np.ndarray:
    """The pixels (flat image indices) that the residual rows of `data` cover, in order:
    those every trace has (`residual_args`); row `3 i + c` is channel `c` of pixel `i`."""
    if len(data) == 1:
        return np.asarray(data[0].pix)
    return functools.reduce(np.intersect1d, [d.pix for d in data])


def residual_args(data: list[TraceData], media0: dict, loss_scale, dt) -> Args:
    """The `Args` of the traces in `data` (independent traces of the same target, averaged
    on the pixels they share), with unit weights; `media0` by name, at the traced `eta`.

    Averaging the traces' models (rather than fitting each trace to the target) is one trace
    with K times the samples: the fit trace's own noise, which a least-squares fit lowers by
    moving toward the coefficients whose image is least noisy (an errors-in-variables bias:
    sharper kernels lean on the per-pixel near field rather than the noisy cloud), falls
    as 1/K instead of staying."""
    if len(data) > 1:
        common = row_pixels(data)
        sel = []
        for d in data:
            order_p = np.argsort(d.pix)
            sel.append(order_p[np.searchsorted(d.pix[order_p], common)])
    else:
        sel = [None]
    tgt_flat = data[0].target if sel[0] is None else data[0].target[sel[0]]
    base = np.mean(
        [d.base if s is None else d.base[:, s] for d, s in zip(data, sel, strict=True)], axis=0
    )
    scale = float(np.mean(np.abs(tgt_flat))) or 1.0  # residuals in units of the mean level
    order = data[0].materials
    # eta is held in a fit: fold its Fresnel factors into the terms once, here
    etas = [media0[m].eta for m in order]

    def group(g: int) -> Any:
        parts = [
            d.terms[g] if s is None else d.terms[g].rows(jnp.asarray(s))
            for d, s in zip(data, sel, strict=True)
        ]
        return type(parts[0]).mean(parts).prepare(etas)

    terms = tuple(group(g) for g in range(len(data[0].terms)))
    halves = tuple(t.halves() for t in terms)
    return Args(
        terms=terms,
        halves=halves if all(h is not None for h in halves) else None,
        target=jnp.asarray(tgt_flat / scale, dtype=dt),
        media0=tuple(media0[m] for m in order),
        scale=jnp.asarray(scale, dtype=dt),
        loss_scale=jnp.asarray(loss_scale, dtype=dt),
        base=jnp.asarray(base / scale, dtype=dt),
        weights=jnp.ones(tgt_flat.shape, dtype=dt),
    )


@eqx.filter_jit
def model(layout: Layout, y, args: Args, terms=None):
    """The fitted pixels' radiance at the solver's coordinates `y`, in units of the target's
    mean: each light group's shading (of `terms`, default `args.terms`), scaled by its free
    intensity factor (groups past the free lights are held at 1), summed, times the
    exposure."""
    n_c = 3 * len(layout.free)
    media = layout.media(y[:n_c], args.media0)
    out = 0.0
    for g, t in enumerate(args.terms if terms is None else terms):
        L = t.shade(media) / args.scale + args.base[g]
        out = out + (jnp.exp(y[n_c + g]) * L if g < layout.n_lights else L)
    return jnp.exp(y[-1]) * out if layout.exposure else out


@functools.lru_cache(maxsize=32)
def residual_fn(layout: Layout, loss: str = "l2", decorrelated: bool = False):
    """`residuals(y, args)`: weighted model - target, through the robust `loss` transform.

    `decorrelated` (terms that are samples, `Args.halves`): the residuals of the two
    independent halves of the terms, stacked `(2, N)`, for a solver that minimises
    `0.5 sum r_A r_B` (`sssjax._solvers`, `decorrelated=True`). A least-squares fit to a
    noisy model leans toward the coefficients whose image is least noisy (the model's
    variance is part of `E |t - m|^2`); the expectation of `(t - m_A)(t - m_B)` carries no
    model variance, so its minimum is, in expectation, that of the noise-free model."""
    transform = LOSSES[loss]

    def residuals(y, args):
        if not decorrelated:
            r = ((model(layout, y, args) - args.target) * args.weights).reshape(-1)
            return transform(r, args.loss_scale)
        halves = [tuple(h[i] for h in args.halves) for i in (0, 1)]
        r = [((model(layout, y, args, t) - args.target) * args.weights).reshape(-1) for t in halves]
        return transform(jnp.stack(r), args.loss_scale)

    return residuals


@dataclasses.dataclass
class FitProblem:
    """A fit of `scene` to `target`: the free parameters (`sssjax.params`), their starting
    values, the options, and how to trace (the renderer, light groups and keys)."""

    scene: Scene
    target: np.ndarray  # (H, W, 3) linear radiance
    free: list[Parameter]  # every free parameter, as resolved
    start: dict[str, Any]  # starting values by parameter name
    options: FitOptions
    mask: np.ndarray | None  # the user's, or None: every pixel with terms but highlights
    seed: Any
    progress: bool = False
    trace_time: float = 0.0  # seconds spent tracing so far
    fit_mask: np.ndarray | None = None  # the mask in use (the first trace's, without one)
    # a re-weighting transport's proposal media by material (None: the scene's); the fit
    # moves it to its solution between solves (`sssjax.fit._solve.run`)
    proposal: dict | None = None
    # the first trace's fitted pixels (flat indices): every later trace fits the same ones
    # (`trace_data`'s `fixed`), so the rows do not depend on a trace's own samples
    fixed: np.ndarray | None = None

    @classmethod
    def build(cls, scene, target, params, init, mask, seed, options, progress) -> FitProblem:
        """Validate everything a fit is given (one-line `FitError`s)."""
        cam = scene.camera
        tgt = load_target(target, (cam.height, cam.width))
        free, start = cls.checked_params(scene, params, init, options)
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != (cam.height, cam.width):
                raise FitError(f"mask has shape {mask.shape}, expected {(cam.height, cam.width)}")
        return cls(scene, tgt, free, start, options, mask, seed, progress, fit_mask=mask)

    @staticmethod
    def checked_params(scene, params, init, options) -> tuple[list[Parameter], dict]:
        """The free parameters and their starting values, checked against the scene and its
        transport (one-line `FitError`s): what a fit file is checked for when it is read,
        before any target is rendered. **Returns:** `(free, start by name)`."""
        try:
            free = _params.resolve(scene, params)
            given = {_params.canonical(scene, k): v for k, v in (init or {}).items()}
        except ParameterError as e:
            raise FitError(str(e)) from None
        names = [p.name for p in free]
        extra = sorted(set(given) - set(names))
        if extra:
            raise FitError(f"init names parameters that are not free: {extra}")
        try:
            start = {p.name: p.initial(given.get(p.name), ETA_RANGE) for p in free}
        except ParameterError as e:
            raise FitError(str(e)) from None
        if TRANSPORTS.get_entry(scene.sss.transport).reweighted:
            g_free = [p.name for p in free if p.field == "g"]
            if g_free:
                raise FitError(
                    f"{g_free[0]}: the {scene.sss.transport} transport cannot fit g (its "
                    "walks are sampled with the scene's phase function and re-weighted in "
                    "sigma_a and sigma_s only): set g in the scene and fit the others"
                )
            eta_free = [p.name for p in free if p.enters is Enters.RETRACED]
            if eta_free:
                # a profile search over re-traces, each solved on one trace far from its
                # proposal, measured eta 1.70 +- 0.003 against 1.30 on the skin slab
                raise FitError(
                    f"{eta_free[0]}: the {scene.sss.transport} transport cannot fit eta (it "
                    "bends the walks, so it cannot be re-weighted): set eta in the scene, or "
                    'measure it on a flat sample with transport = "diffusion" and profile = '
                    '"tabulated"'
                )
            if scene.render.spp % 2:
                # checked before the target is rendered and traced, not after
                raise FitError(
                    f"spp = {scene.render.spp}: a fit with the {scene.sss.transport} "
                    "transport splits each pixel's walks into two independent halves: use "
                    "an even spp"
                )
            if options.proposal_rounds < 1:
                raise FitError(
                    f"proposal_rounds must be >= 1 with the {scene.sss.transport} transport "
                    "(its fit is re-traced rounds), got 0"
                )
        return free, start

    # -- what the coordinates are --------------------------------------------------------
    def _of(self, enters: Enters) -> list[Parameter]:
        return [p for p in self.free if p.enters is enters]

    @property
    def eta(self) -> Parameter | None:
        """The free refractive index (re-traced), if any."""
        eta = self._of(Enters.RETRACED)
        return eta[0] if eta else None

    @property
    def lights(self) -> list[int]:
        return sorted(p.light for p in self._of(Enters.EMISSION))

    @property
    def layout(self) -> Layout:
        free = tuple((p.material, p.field) for p in self._of(Enters.SHADED))
        order = tuple(self.scene.translucent_materials)
        return Layout(free, order, bool(self._of(Enters.IMAGE)), len(self.lights))

    @property
    def names(self) -> list[str]:
        """The solver's coordinates by name (`marble.sigma_a.R`, ..., `lights.N`, `exposure`)."""
        names = [f"{p.name}.{_CH[c]}" for p in self._of(Enters.SHADED) for c in range(3)]
        return names + [f"lights.{i}" for i in self.lights] + ["exposure"] * self.layout.exposure

    @property
    def tanh_idx(self) -> np.ndarray:
        """Which coordinates are atanh (of `g`); the others are logs."""
        coef = [p.field == "g" for p in self._of(Enters.SHADED) for _ in range(3)]
        return np.array(coef + [False] * (len(self.lights) + self.layout.exposure))

    @property
    def y0(self) -> Array:
        """The starting coordinates: log of the coefficients, light factors and the
        exposure, atanh of `g`."""
        parts = []
        for p in self._of(Enters.SHADED):
            v = self.start[p.name]
            parts.append(np.arctanh(v) if p.field == "g" else np.log(v))
        parts += [[np.log(self.start[f"lights.{i}"])] for i in self.lights]
        if self.layout.exposure:
            parts.append([np.log(self.start["exposure"])])
        return jnp.asarray(np.concatenate(parts))

    def values(self, y) -> np.ndarray:
        """Parameter values from the solver's coordinates (float64 NumPy)."""
        y = np.asarray(y, dtype=np.float64)
        t = self.tanh_idx[: y.size]
        return np.where(t, np.tanh(y), np.exp(np.where(t, 0.0, y)))

    # -- tracing -------------------------------------------------------------------------
    @functools.cached_property
    def renderer(self):
        return renderer_for(self.scene)

    @property
    def key(self):
        return as_key(self.seed, self.scene)

    @property
    def reweighted(self) -> bool:
        """Whether the transport's traces are re-weighted samples of a proposal (then the
        fit re-traces at its solution)."""
        return self.renderer.transport.reweighted

    def media_at(self, y, media: dict) -> dict:
        """The media by material with the free coefficients at `y` (float64 NumPy), the rest
        as in `media`."""
        layout = self.layout
        order = layout.order
        fitted = layout.media(jnp.asarray(y), [media[n] for n in order])
        return {
            n: Medium(*(np.asarray(v, np.float64) for v in (m.sigma_a, m.sigma_s, m.g)), m.eta)
            for n, m in zip(order, fitted, strict=True)
        }

    def trace_keys(self) -> list:
        """The keys of the `traces` independent traces."""
        k0 = self.key
        return [
            k0 if k == 0 else jax.random.fold_in(k0, 1000 + k) for k in range(self.options.traces)
        ]

    def traced(self, keys, eta: float | None = None) -> tuple[list[TraceData], dict]:
        """The data of the traces `keys` (one trace per light group each) and the media,
        at the free material's `eta` if given (it bends the rays: a re-trace, with the
        compiled tracer). The first trace's mask (highlights left out) and fitted pixels hold
        for the rest."""
        t = time.perf_counter()
        media = dict(self.scene.media())
        etas = None
        if eta is not None:
            mat = self.eta.material
            etas = {mat: eta}
            m = media[mat]
            media[mat] = Medium(m.sigma_a, m.sigma_s, m.g, eta)
        gains = light_groups(len(self.scene.lights), self.lights)
        data = []
        for k in keys:
            d = trace_data(
                self.renderer,
                gains,
                k,
                self.target,
                self.fit_mask,
                self.progress,
                etas,
                self.proposal,
                self.fixed,
            )
            if self.fit_mask is None and self.progress:
                n_hl = len(d.all_pix) - len(d.pix)
                print(
                    f"fitting {len(d.target)} translucent pixels"
                    + (f" ({n_hl} highlight pixels left out)" if n_hl else ""),
                    file=sys.stderr,
                    flush=True,
                )
            self.fit_mask = d.mask
            self.fixed = d.pix if self.fixed is None else self.fixed
            data.append(d)
        self.trace_time += time.perf_counter() - t
        return data, media

    def args(self, data, media, dt, weights_at=None, weights_from=None) -> Args:
        """The residual functions' data for `data` and `media`, weighted as the options say:
        relative weights from the target's values, or from the model's at `weights_at` (of
        the traces `weights_from` when given: independent of `data`'s noise, which weights
        from `data`'s own model would favour, as the target's own values favour its)."""
        args = residual_args(data, media, self.options.loss_scale, dt)
        weighting = WEIGHTINGS[self.options.weighting]
        if weighting.weights is None:
            return args
        if weights_from is not None:
            other = residual_args(weights_from, media, self.options.loss_scale, dt)
            level = np.asarray(model(self.layout, weights_at, other))
            level = level * float(other.scale) / float(args.scale)
        elif weights_at is None:
            level = np.asarray(args.target)  # the target, in units of its mean
        else:
            level = np.asarray(model(self.layout, weights_at, args))
        w = weighting.weights(level, self.options.rel_floor)
        return eqx.tree_at(lambda a: a.weights, args, jnp.asarray(w, dtype=dt))
