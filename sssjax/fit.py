"""Fitting scattering coefficients to images: where the measurement happens.

`fit(scene, target, ...)` traces the scene once (`trace`) and then runs optimistix's
Levenberg-Marquardt (default) or Gauss-Newton on pixel residuals of `shade`, in the log of
the coefficients, with forward-mode Jacobians (few parameters, many pixels). Every iteration
only re-shades: no ray is cast inside the loop. The result carries standard errors from the
Gauss-Newton covariance `s^2 (J^T J)^-1` at the solution (mapped from log space by the delta
method), the correlation matrix, the history and the solver's status.

Coefficients in mm^-1.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from scipy.ndimage import binary_dilation

from ._numerics import safe_sqrt
from ._solvers import NormalGaussNewton, NormalLevenbergMarquardt
from .media import Medium
from .render import as_key, renderer_for
from .scene import Scene, did_you_mean

__all__ = ["fit", "FitResult", "FitError", "PARAM_FIELDS"]

PARAM_FIELDS = ("sigma_a", "sigma_s", "sigmap_s", "g", "eta")
ETA_RANGE = (1.0, 2.5)  # the refractive indices a fit of eta searches (exclusive of 1)
_CH = "RGB"
HIGHLIGHT_LEVEL = 4.0  # a highlight is this many times the translucent pixels' median


class FitError(ValueError):
    """Bad fit input (target, mask, parameters, initial guess): a one-line message."""


@dataclasses.dataclass
class FitResult:
    """What a fit found and how sure it is.

    `values`, `stderr`: per parameter name (`"marble.sigma_a.R"`), in mm^-1.
    `correlation`: parameter correlation matrix (order of `names`).
    """

    names: list[str]
    values: dict[str, float]
    stderr: dict[str, float]
    initial: dict[str, float]
    correlation: list[list[float]]
    media: dict[str, Medium]
    steps: int
    loss_initial: float
    loss_final: float
    status: str
    message: str
    converged: bool
    wall_time_s: float
    trace_time_s: float
    history: list[dict[str, Any]]
    warnings: list[str]
    trace_stderr: dict[str, float] | None = None  # from `refine`: the trace-noise part
    # with `eta` free: every refractive index tried, with the loss of the fit there
    eta_search: list[dict[str, float]] | None = None
    pixels: int = 0  # pixels fitted (with several traces: the ones they all see)
    highlight_pixels: int = 0  # translucent pixels left out as highlights (no user mask)
    # `(H, W)` the highlight pixels left out (not in the JSON)
    highlights: np.ndarray | None = dataclasses.field(default=None, repr=False)

    @property
    def exposure(self) -> float:
        """The fitted exposure factor (1 when it was not free)."""
        return float(self.values.get("exposure", 1.0))

    def apply(self, scene: Scene) -> Scene:
        """`scene` with what the fit found: the fitted media (their `eta` too) and each free
        light's emission scaled by its factor. `render(result.apply(scene)) * result.exposure`
        is the fitted image."""
        mats = dict(scene.materials)
        for name, med in self.media.items():
            mats[name] = dataclasses.replace(mats[name], medium=med)
        lights = list(scene.lights)
        for n, v in self.values.items():
            if n.startswith("lights."):
                lt = lights[int(n.removeprefix("lights."))]
                f = _EMISSION[type(lt).__name__]
                lights[int(n.removeprefix("lights."))] = dataclasses.replace(
                    lt, **{f: np.asarray(getattr(lt, f)) * v}
                )
        return scene.replace(materials=mats, lights=tuple(lights))

    def to_json(self, path: str | Path | None = None) -> str:
        """The result as JSON (media as coefficient lists); written to `path` if given."""
        d = dataclasses.asdict(self)
        d.pop("highlights")
        d["media"] = {
            n: {
                "sigma_a": np.asarray(m.sigma_a).tolist(),
                "sigma_s": np.asarray(m.sigma_s).tolist(),
                "sigmap_s": np.asarray(m.sigmap_s).tolist(),
                "g": np.asarray(m.g).tolist(),
                "eta": float(m.eta),
            }
            for n, m in self.media.items()
        }
        d["units"] = "coefficients in 1/mm"
        text = json.dumps(d, indent=2)
        if path is not None:
            Path(path).write_text(text)
        return text

    def summary(self) -> str:
        lines = [f"{'parameter':<24} {'value':>10} {'std err':>10} {'initial':>10}"]
        for n in self.names:
            lines.append(
                f"{n:<24} {self.values[n]:10.5g} {self.stderr[n]:10.2g} {self.initial[n]:10.5g}"
            )
        lines.append(
            f"{self.steps} steps, loss {self.loss_initial:.4g} -> {self.loss_final:.4g}, "
            f"{self.status}: {self.message}"
        )
        if self.highlight_pixels:
            lines.append(
                f"{self.pixels} pixels fitted; {self.highlight_pixels} highlight pixels "
                "(mostly mirror-reflected light, independent of the coefficients) left out"
            )
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _resolve_params(
    scene: Scene, params: Sequence[str] | None
) -> tuple[list[tuple[str, str]], bool, list[int], str | None]:
    """The free `(material, field)` pairs, whether the exposure is free, the indices of
    the lights whose intensity is free, and the material whose `eta` is free (or None)."""
    tm = scene.translucent_materials
    if not tm:
        raise FitError("the scene has no translucent material to fit")
    if params is None:
        return [(m, f) for m in tm for f in ("sigma_a", "sigma_s")], False, [], None
    out = []
    exposure = "exposure" in params
    lights = []
    for p in params:
        if p == "exposure":
            continue
        if p.startswith("lights."):
            idx = p.removeprefix("lights.")
            n = len(scene.lights)
            if not (idx.isdigit() and int(idx) < n):
                raise FitError(
                    f"parameter {p!r}: no such light (the scene has {n}: lights.0 .. "
                    f"lights.{n - 1})"
                    if n
                    else f"parameter {p!r}: the scene has no lights"
                )
            if int(idx) not in lights:
                lights.append(int(idx))
            continue
        mat, _, field = p.rpartition(".")
        if not mat:
            if len(tm) != 1:
                raise FitError(
                    f"parameter {p!r}: name the material ({', '.join(tm)}), e.g. '{tm[0]}.{p}'"
                )
            mat = tm[0]
        if mat not in tm:
            raise FitError(
                f"parameter {p!r}: no translucent material {mat!r} (known: {', '.join(tm)})"
            )
        if field not in PARAM_FIELDS:
            known = ", ".join((*PARAM_FIELDS, "exposure", "lights.N"))
            hint = did_you_mean(field, [*PARAM_FIELDS, "exposure"])
            raise FitError(f"unknown parameter {field!r}{hint} (known: {known})")
        out.append((mat, field))
    for mat in tm:
        fields = {f for m, f in out if m == mat}
        if {"sigma_s", "sigmap_s"} <= fields:
            raise FitError(f"{mat}: free either sigma_s or sigmap_s, not both")
    eta_mats = sorted({m for m, f in out if f == "eta"})
    if len(eta_mats) > 1:
        raise FitError(f"params: free the eta of one material at a time, got {eta_mats}")
    out = [(m, f) for m, f in out if f != "eta"]
    if not out:
        raise FitError(
            "params: free at least one coefficient (exposure or light intensities alone fit "
            "no material)"
        )
    if lights and len(lights) == len(scene.lights) and exposure:
        raise FitError(
            "params: the exposure and every light's intensity are free, but only their "
            "product is determined: fix the exposure or one light"
        )
    return out, exposure, sorted(lights), (eta_mats[0] if eta_mats else None)


def _load_target(target, shape: tuple[int, int]) -> np.ndarray:
    if isinstance(target, str | Path):
        from .imageio import read_image

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


def fit(
    scene: Scene,
    target,
    *,
    params: Sequence[str] | None = None,
    init: dict[str, Any] | None = None,
    mask=None,
    seed=None,
    solver: str = "lm",
    max_steps: int = 50,
    rtol: float = 1e-5,
    atol: float = 1e-6,
    loss: str = "l2",
    loss_scale: float = 0.1,
    weighting: str = "absolute",
    rel_floor: float = 0.01,
    traces: int = 1,
    refine: bool = False,
    progress: bool = False,
) -> FitResult:
    """Recover scattering coefficients of the scene's translucent materials from `target`.

    **Arguments:**

    - `scene`: the scene the target was taken in (camera, lights, geometry).
    - `target`: `(H, W, 3)` linear radiance, or an image path (EXR/PNG/TIFF).
    - `params`: free parameters, `"MATERIAL.FIELD"` with FIELD in `sigma_a`, `sigma_s`,
      `sigmap_s` (each RGB, mm^-1), `g` (the Henyey-Greenstein mean cosine, RGB; the
      diffusion term sees only `sigmap_s = sigma_s (1 - g)`, so `g` is separated from
      `sigma_s` by single scattering alone) (the material may be omitted when there is
      only one), and
      `"exposure"`: one overall factor on the rendered image (a nuisance parameter for an
      uncalibrated camera or light), and `"lights.N"`: a factor on the emission of the
      scene's `N`-th light (0-based, in `[[lights]]` order; radiance, intensity or power
      alike), for lamps of unknown relative power. Each free light costs one more trace
      (the image is linear in each light's emission, so the fit traces each free light
      alone and shades their sum); with every light free, the exposure must be fixed.
      Default: `sigma_a` and `sigma_s` of every translucent material.
    - `init`: initial values by `"MATERIAL.FIELD"` (RGB, mm^-1, > 0; `g` in (-1, 1)),
      `"exposure"` or `"lights.N"` (factors > 0);
      default: the scene's (exposure 1).
    - `mask`: `(H, W)` boolean pixels to fit; default: every pixel that sees a translucent
      object (the only pixels the coefficients affect) except highlights, pixels whose
      radiance is mostly coefficient-independent (a lamp's or a bright floor's mirror
      reflection), grown by one pixel: their jittered edges differ between traces by
      hundreds of times the subsurface signal. `result.highlight_pixels` counts them.
    - `seed`: trace seed (default the scene's).
    - `traces`: number of independent traces averaged into the fitted model (default 1):
      one trace with K times the samples. A trace's noise is shared by all its pixels, and
      a least-squares fit leans toward coefficients whose image is less noisy, so a single
      trace biases the fit by more than its per-pixel error bars say; K traces cut that
      noise by K, at K times the trace time (the per-iteration cost barely grows).
    - `refine`: after the fit, trace again with a fresh seed, fit that trace alone from the
      solution, then fit the average of both. The final values are the joint fit; the difference
      between the two single-trace fits measures the trace noise, which is reported in
      `trace_stderr` and added (in quadrature) to `stderr`.
    - `solver`: `"lm"` (Levenberg-Marquardt), `"gn"` (Gauss-Newton) or `"bfgs"` (on the
      scalar loss).
    - `weighting`: `"absolute"` residuals in units of the target's mean level, or
      `"relative"`: each pixel's residual divided by its target value (plus `rel_floor`
      times the mean level), for targets spanning decades such as a beam-lit slab, where
      absolute residuals let the brightest pixels decide everything.
    - `loss`: `"l2"`, or a robust `"cauchy"` / `"huber"` for photographs with outliers
      (specular highlights, dust); `loss_scale` is their transition, in units of the
      (weighted) residual. Error bars then come from the transformed residuals.

    **Returns:** a `FitResult`. A fit that fails to converge says so in `status`/`message`.
    """
    t_start = time.perf_counter()
    cam = scene.camera
    tgt = _load_target(target, (cam.height, cam.width))
    free, exposure, lights, eta_mat = _resolve_params(scene, params)
    media0 = scene.media()
    init = dict(init or {})
    start = {}
    for mat, field in free:
        m = media0[mat]
        v = np.asarray(getattr(m, field), dtype=np.float64)
        for key in (f"{mat}.{field}", field):
            if key in init:
                v = np.broadcast_to(np.asarray(init.pop(key), dtype=np.float64), (3,))
                break
        v = np.broadcast_to(v, (3,))
        if field == "g":
            if not np.all(np.isfinite(v)) or np.any(np.abs(v) >= 1):
                raise FitError(f"initial {mat}.g must satisfy |g| < 1, got {v.tolist()}")
        elif not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise FitError(f"initial {mat}.{field} must be finite and > 0, got {v.tolist()}")
        start[(mat, field)] = v
    e0 = float(np.asarray(init.pop("exposure", 1.0), dtype=np.float64)) if exposure else 1.0
    if not (np.isfinite(e0) and e0 > 0):
        raise FitError(f"initial exposure must be finite and > 0, got {e0}")
    light0 = []
    for i in lights:
        v = init.pop(f"lights.{i}", 1.0)
        v = float(np.asarray(v, dtype=np.float64)) if np.ndim(v) == 0 else np.nan
        if not (np.isfinite(v) and v > 0):
            raise FitError(f"initial lights.{i} must be one finite factor > 0, got {v}")
        light0.append(v)
    if eta_mat is not None:
        v = init.pop(f"{eta_mat}.eta", init.pop("eta", float(media0[eta_mat].eta)))
        eta_init = float(np.asarray(v, dtype=np.float64)) if np.ndim(v) == 0 else np.nan
        if not (ETA_RANGE[0] < eta_init < ETA_RANGE[1]):
            raise FitError(
                f"initial {eta_mat}.eta must be one number in ({ETA_RANGE[0]}, "
                f"{ETA_RANGE[1]}), got {v}"
            )
    if init:
        raise FitError(f"init names parameters that are not free: {sorted(init)}")
    if not (isinstance(traces, int) and traces >= 1):
        raise FitError(f"traces must be an integer >= 1, got {traces!r}")
    if loss not in ("l2", "cauchy", "huber"):
        raise FitError(f"unknown loss {loss!r} (known: l2, cauchy, huber)")
    if not loss_scale > 0:
        raise FitError(f"loss_scale must be > 0, got {loss_scale}")
    if weighting not in ("absolute", "relative"):
        raise FitError(f"unknown weighting {weighting!r} (known: absolute, relative)")
    if not rel_floor > 0:
        raise FitError(f"rel_floor must be > 0, got {rel_floor}")
    if solver not in ("lm", "gn", "bfgs"):
        raise FitError(f"unknown solver {solver!r} (known: lm, gn, bfgs)")

    # one trace per free light (only it emitting) and one for the other lights: the image is
    # linear in each light's emission, so the fit scales and sums their shadings
    renderer = renderer_for(scene)
    gains = _light_groups(len(scene.lights), lights)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (cam.height, cam.width):
            raise FitError(f"mask has shape {mask.shape}, expected {(cam.height, cam.width)}")
    key0 = as_key(seed, scene)
    trace_clock = [0.0]  # seconds spent tracing
    fit_mask = [mask]  # None: every translucent pixel but the highlights (first trace)
    # several independent traces average out the noise that one trace (its irradiance
    # cloud above all) shares across every pixel, which a single trace fits as signal
    keys = [key0 if k == 0 else jax.random.fold_in(key0, 1000 + k) for k in range(traces)]

    def traced(keys, eta=None):
        """The fit data of `keys` and the media, at the free material's `eta` if given
        (it bends the rays: a re-trace, with the compiled tracer)."""
        t = time.perf_counter()
        media = dict(media0)
        etas = None
        if eta is not None:
            etas = {eta_mat: eta}
            m = media0[eta_mat]
            media[eta_mat] = Medium(m.sigma_a, m.sigma_s, m.g, eta)
        data = []
        for k in keys:
            data.append(_trace_data(renderer, gains, k, tgt, fit_mask[0], progress, media, etas))
            # the first trace's highlight-free mask holds for every later trace and eta
            if fit_mask[0] is None and progress:
                n_hl = len(data[-1]["all_pix"]) - len(data[-1]["pix"])
                print(
                    f"fitting {len(data[-1]['tgt'])} translucent pixels"
                    + (f" ({n_hl} highlight pixels left out)" if n_hl else ""),
                    file=sys.stderr,
                    flush=True,
                )
            fit_mask[0] = data[-1]["mask"]
        trace_clock[0] += time.perf_counter() - t
        return data, media

    names = [f"{m}.{f}.{_CH[c]}" for m, f in free for c in range(3)]
    names += [f"lights.{i}" for i in lights] + ["exposure"] * exposure
    # unconstrained coordinates: log of the coefficients, light factors and the exposure,
    # atanh of g
    tanh_idx = np.array(
        [f == "g" for _, f in free for _ in range(3)] + [False] * (len(lights) + exposure)
    )
    y0 = jnp.asarray(
        np.concatenate(
            [np.arctanh(start[k]) if k[1] == "g" else np.log(start[k]) for k in free]
            + [np.log(np.asarray(light0, dtype=np.float64))]
            + [[np.log(e0)]] * exposure
        )
    )
    fn_kw = dict(
        free=tuple(free),
        exposure=exposure,
        n_lights=len(lights),
        loss=loss,
        solver=solver,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        loss_scale=loss_scale,
        weighting=weighting,
        rel_floor=rel_floor,
        names=names,
        tanh_idx=tanh_idx,
        progress=progress,
    )
    eta_star, eta_search = None, None
    y_start = y0
    if eta_mat is not None:
        eta_star, eta_search, y_start, eta_loss0, eta_bounds, (data, media_fit) = _search_eta(
            lambda eta: traced(keys, eta), y0, eta_init, eta_mat, fn_kw, progress
        )
    else:
        data, media_fit = traced(keys)
    fn_kw["media0"] = media_fit
    run = _solve(data, y_start, **fn_kw)
    if weighting == "relative":
        # weights from the target's own noisy values favour pixels whose noise happens to be
        # low and so bias the fit (by about the pixels' relative variance); refit with
        # weights from the fitted model instead, which does not share the target's noise
        run = _solve(data, run["y"], weights_at=run["y"], **fn_kw)
    trace_sd = None
    if refine:
        fresh = traced([jax.random.fold_in(key0, 99_991)], eta_star)[0][0]
        if progress:
            print("refine: fit a fresh trace from the solution", file=sys.stderr, flush=True)
        w_at = run["y"] if weighting == "relative" else None
        other = _solve([fresh], run["y"], weights_at=w_at, **fn_kw)
        if progress:
            print("refine: fit the average of both traces", file=sys.stderr, flush=True)
        joint = _solve(data + [fresh], 0.5 * (run["y"] + other["y"]), weights_at=w_at, **fn_kw)
        keys = keys + [jax.random.fold_in(key0, 99_991)]
        # two single-trace solutions differ by trace noise alone (same target): their
        # half-difference estimates the trace-noise error of the joint (mean) solution
        trace_sd = 0.5 * np.abs(np.asarray(run["y"] - other["y"], dtype=np.float64))
        joint["history"] = run["history"] + other["history"] + joint["history"]
        joint["steps"] = run["steps"] + other["steps"] + joint["steps"]
        run = joint

    y = run["y"]
    order = run["order"]
    J, r = _jac_res(run["residuals"], y, run["args"])
    J, r = np.asarray(J, dtype=np.float64), np.asarray(r, dtype=np.float64)
    if eta_mat is not None:
        # the eta column by central differences of re-traced residuals (same keys, so the
        # same random numbers), the other parameters held at the solution
        h = 2e-3
        cols = []
        for e in (eta_star + h, eta_star - h):
            d_e, m_e = traced(keys, e)
            a_e, _ = _fit_args(d_e, m_e, loss_scale, run["args"][1].dtype)
            a_e = (*a_e[:7], run["args"][7])  # the weights of the final fit
            cols.append(np.asarray(run["residuals"](y, a_e), dtype=np.float64))
        J = np.concatenate([J, ((cols[0] - cols[1]) / (2 * h))[:, None]], axis=1)
        names = names + [f"{eta_mat}.eta"]
        tanh_idx = np.append(tanh_idx, False)
    dof = max(r.size - J.shape[1], 1)
    s2 = float(r @ r) / dof
    JtJ = J.T @ J
    warnings = []
    try:
        cond = np.linalg.cond(JtJ)
        inv = np.linalg.inv(JtJ)
        cov_log = s2 * inv
        # the pixels' noise is far from uniform (steep profile regions are noisier), and the
        # information sits in particular pixels: the heteroscedasticity-consistent
        # "sandwich" covariance (White 1980) is honest then; take the larger of the two
        cov_hc = inv @ ((J * (r**2 * r.size / dof)[:, None]).T @ J) @ inv  # HC1
        # a numerically singular J^T J can give a negative diagonal: no ratio there (the
        # parameter's error bar is then infinite, below)
        d_log = np.diag(cov_log)
        ok = d_log > 0
        scale_hc = np.ones_like(d_log)
        scale_hc[ok] = np.sqrt(np.clip(np.diag(cov_hc)[ok], 0, None) / d_log[ok])
        scale_hc = np.maximum(np.nan_to_num(scale_hc, nan=1.0), 1.0)
        cov_log = cov_log * np.outer(scale_hc, scale_hc)
        if not np.isfinite(cond) or cond > 1e12:
            warnings.append(
                f"the covariance is near-singular (condition number {cond:.2g}): some "
                "parameters are not identifiable from this target; their errors are unreliable"
            )
    except np.linalg.LinAlgError:
        cov_log = np.full((J.shape[1], J.shape[1]), np.inf)
        warnings.append("J^T J is singular: the parameters are not identifiable from this target")
    vals = _values(y, tanh_idx[: y.size])
    # d value / d y: value for log coordinates, 1 - g^2 for atanh
    dval = np.where(tanh_idx[: y.size], 1.0 - vals**2, vals)
    if eta_mat is not None:  # eta is its own coordinate
        vals, dval = np.append(vals, eta_star), np.append(dval, 1.0)
    diag = np.diag(cov_log)
    # a negative variance is a numerically singular J^T J: that parameter is not determined
    sd_log = np.where(diag >= 0, np.sqrt(np.abs(diag)), np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_log / np.outer(sd_log, sd_log)
    trace_stderr = None
    if trace_sd is not None:
        if eta_mat is not None:
            trace_sd = np.append(trace_sd, 0.0)  # refine re-fits the others at eta*
        trace_stderr = dict(zip(names, (dval * trace_sd).tolist(), strict=True))
        sd_log = np.sqrt(sd_log**2 + trace_sd**2)
        ratio = np.max(trace_sd / np.maximum(np.sqrt(np.abs(np.diag(cov_log))), 1e-300))
        if ratio > 2:
            warnings.append(
                f"trace noise dominates the error (up to {ratio:.0f}x the statistical "
                "error): use more traces, a larger cloud_size or more spp"
            )
    fields = {f for _, f in free}
    if "sigma_s" in fields and not scene.sss.single_scattering:
        warnings.append(
            "sigma_s is free but single scattering is off: the dipole sees only "
            "sigmap_s = sigma_s (1 - g)"
        )
    for mat in {m for m, _ in free}:
        if (mat, "g") in free and ((mat, "sigma_s") in free or (mat, "sigmap_s") in free):
            other = "sigma_s" if (mat, "sigma_s") in free else "sigmap_s"
            idx = {n: i for i, n in enumerate(names)}
            rho = max(abs(corr[idx[f"{mat}.g.{c}"], idx[f"{mat}.{other}.{c}"]]) for c in _CH)
            if not scene.sss.single_scattering or not np.isfinite(rho) or rho > 0.95:
                why = "is off" if not scene.sss.single_scattering else "is too weak"
                warnings.append(
                    f"{mat}: g and {other} are both free, but the diffusion term sees only "
                    f"sigmap_s = sigma_s (1 - g) and single scattering {why} to separate "
                    f"them (correlation up to {rho:.3f}): fix g, or fit sigmap_s alone"
                )
    if exposure and "sigma_a" in fields:
        warnings.append(
            "exposure is free: the absolute level no longer pins the albedo, so sigma_a rests "
            "on the shape of the image alone (see its error bar)"
        )
    converged, status, message = run["converged"], run["status"], run["message"]
    steps = run["steps"]
    loss_initial = float(_loss(run["residuals"], y0, run["args"]))
    if eta_mat is not None:
        steps += sum(t["steps"] for t in eta_search)
        loss_initial = eta_loss0  # at the initial eta, not the fitted one
        if min(abs(eta_star - b) for b in eta_bounds) < 1e-3:
            warnings.append(
                f"{eta_mat}.eta = {eta_star:.4f} is at the edge of the searched range "
                f"{eta_bounds[0]:.3f}..{eta_bounds[1]:.3f}: start nearer, or fix eta"
            )
    if not converged:
        moved = np.abs(np.asarray(y - y0, dtype=np.float64)) > np.log(10.0)
        far = [n for n, m, t in zip(names, moved, tanh_idx, strict=True) if m and not t]
        if far:
            warnings.append(
                f"no convergence, and {', '.join(far)} moved more than 10x from the start: "
                "the minimum may lie at the edge (e.g. sigma_a -> 0 when the target is "
                "brighter than the scene allows); check the target's exposure and outliers "
                "(loss='cauchy', or free the exposure)"
            )
    # an unidentified parameter has an infinite error bar (not 0 x inf = nan)
    stderr = np.where(np.isfinite(sd_log), dval * np.where(np.isfinite(sd_log), sd_log, 0), np.inf)
    vague = [n for n, sd in zip(names, sd_log, strict=True) if not sd < 0.5 and n != "exposure"]
    if vague:
        warnings.append(
            f"{', '.join(vague)}: not determined by this target (error bar beyond +-50%): "
            "fix them, or use a measurement that constrains them"
        )
    # a loss carried by a handful of pixels is an outlier fit, not a measurement
    r2 = np.sort(r**2)[::-1]
    n_top = max(1, r.size // 1000)
    share = float(r2[:n_top].sum() / max(r2.sum(), 1e-300))
    if share > 0.5 and r.size >= 1000:
        warnings.append(
            f"{share:.0%} of the loss comes from {n_top} of {r.size} residuals: outliers "
            "(highlights, dust, saturated pixels); mask them, or use loss='cauchy'"
        )
    highlights = None if mask is not None else _left_out(data[0], tgt.shape[:2])
    y_media = y[: 3 * len(free)]
    fitted = dict(zip(order, _media_of(tuple(free), order, y_media, run["args"][3]), strict=True))
    return FitResult(
        names=names,
        values=dict(zip(names, vals.tolist(), strict=True)),
        stderr=dict(zip(names, stderr.tolist(), strict=True)),
        initial=dict(
            zip(
                names,
                _values(y0, tanh_idx[: y0.size]).tolist() + ([eta_init] if eta_mat else []),
                strict=True,
            )
        ),
        correlation=np.nan_to_num(corr).tolist(),
        media=fitted,
        steps=steps,
        loss_initial=loss_initial,
        loss_final=float(_loss(run["residuals"], y, run["args"])),
        status=status,
        message=message,
        converged=bool(converged),
        wall_time_s=time.perf_counter() - t_start,
        trace_time_s=trace_clock[0],
        history=run["history"],
        warnings=warnings,
        trace_stderr=trace_stderr,
        eta_search=eta_search,
        pixels=int(run["args"][1].shape[0]),  # the pixels all traces share
        highlight_pixels=0 if highlights is None else int(highlights.sum()),
        highlights=highlights,
    )


def _left_out(d, shape) -> np.ndarray:
    """`(H, W)` the translucent pixels of trace data `d` that its mask left out."""
    out = np.zeros(shape[0] * shape[1], dtype=bool)
    out[d["all_pix"]] = True
    out[d["pix"]] = False
    return out.reshape(shape)


def _search_eta(traced, y0, eta_init, eta_mat, fn_kw, progress):
    """Minimise the profile loss `min_theta loss(theta; eta)` over the free material's
    refractive index by bounded Brent search. `eta` bends rays, so each value tried is a
    re-trace (same keys: the same random numbers, so the loss is smooth in eta) and a fit of
    the other parameters from the best so far, starting with `eta_init` itself. Weights stay
    the target's throughout, so the losses compare. The search spans `eta_init +- 0.3`
    (within `ETA_RANGE`). **Returns:** `(eta*, [{eta, loss, steps}], y at eta*, the loss at
    y0 and eta_init, the bounds, the best value's `traced` output)`."""
    from scipy.optimize import minimize_scalar

    kw = dict(fn_kw)
    best = {"loss": np.inf, "y": y0}
    tried = []
    first = {}

    def profile_loss(eta):
        data, media = traced(float(eta))
        run = _solve(data, best["y"], media0=media, **dict(kw, progress=False))
        first.setdefault("loss0", run["loss0"])
        loss_val = float(_loss(run["residuals"], run["y"], run["args"]))
        tried.append({"eta": float(eta), "loss": loss_val, "steps": run["steps"]})
        if progress:
            print(
                f"eta search: {eta_mat}.eta = {eta:.5f}  loss {loss_val:.6g}  "
                f"({run['steps']} steps)",
                file=sys.stderr,
                flush=True,
            )
        if loss_val < best["loss"]:
            best.update(loss=loss_val, y=run["y"], eta=float(eta), traced=(data, media))
        return loss_val

    lo = max(ETA_RANGE[0] + 1e-3, eta_init - 0.3)
    hi = min(ETA_RANGE[1], eta_init + 0.3)
    profile_loss(eta_init)  # the loss at the start, and a warm start for the search
    minimize_scalar(profile_loss, bounds=(lo, hi), method="bounded", options={"xatol": 2e-4})
    return best["eta"], tried, best["y"], first["loss0"], (lo, hi), best["traced"]


_EMISSION = {"AreaLight": "radiance", "PointLight": "intensity", "BeamLight": "power"}


def _light_groups(n_lights: int, free_lights: Sequence[int]) -> list[np.ndarray | None]:
    """Per-light emission factors of traces whose transports add up to the scene's: one per
    free light (only that light emitting), then one with the other lights (absent when
    every light is free); `[None]` (the scene as it is) when no light is free. Every light
    stays in the scene, dark or not, so rays, samples and random numbers are the scene's and
    each trace is exactly its lights' share."""
    if not free_lights:
        return [None]
    rest = [i for i in range(n_lights) if i not in free_lights]
    groups = [[i] for i in free_lights] + ([rest] if rest else [])
    return [np.isin(np.arange(n_lights), g).astype(np.float64) for g in groups]


def _highlights(pix, base, tgt, shape) -> np.ndarray:
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


def _trace_data(renderer, gains, key, tgt, mask, progress, media0, etas=None):
    """Trace once per light group (`gains`, from `_light_groups`) and keep what the fit
    needs: the subsurface terms of the fitted pixels, their target values and their
    medium-independent radiance (`base`), per group. `mask=None` fits every translucent
    pixel but the highlights (`_highlights`); `data["mask"]` is the mask used."""
    transports = [renderer.trace(key, progress, etas, g) for g in gains]
    transport = transports[0]
    pix = np.asarray(transport.translucent_pixels())
    rows = np.asarray(transport.t_rows)
    if mask is None and len(pix):
        base_all = np.stack([np.asarray(t.base)[rows] for t in transports])
        hl = _highlights(pix, base_all, tgt.reshape(-1, 3)[pix], tgt.shape[:2])
        mask = ~hl
        if not mask.reshape(-1)[pix].any():  # nothing but highlight: fit it all
            mask = np.ones(tgt.shape[:2], dtype=bool)
    if mask is not None:
        rows_sel = np.flatnonzero(mask.reshape(-1)[pix])
        if len(rows_sel) == 0:
            raise FitError("the mask selects no pixel that sees a translucent object")
    else:
        if len(pix) == 0:
            raise FitError("no pixel sees a translucent object: nothing to fit")
        rows_sel = np.arange(len(pix))
    sel = jnp.asarray(rows_sel)
    return dict(
        sub=[t.terms.rows(sel) for t in transports],
        tgt=tgt.reshape(-1, 3)[pix[rows_sel]],
        base=np.stack([np.asarray(t.base)[rows[rows_sel]] for t in transports]),
        r_nodes=transport.r_nodes,
        materials=transport.materials,
        mask=mask,
        pix=pix[rows_sel],  # the fitted pixels (flat image indices)
        all_pix=pix,  # every translucent pixel
    )


def _solve(
    data,
    y0,
    *,
    free,
    exposure,
    n_lights,
    loss,
    media0,
    solver,
    max_steps,
    rtol,
    atol,
    loss_scale,
    weighting,
    rel_floor,
    names,
    tanh_idx,
    progress,
    weights_at=None,
):
    """Run the solver on the traces in `data` (averaged, `_fit_args`) from `y0` (log
    parameters).

    With relative weighting, each pixel's weight is `1 / (value / mean + rel_floor)` with
    `value` the target's, or the model's at `weights_at` when given."""
    dt = jnp.float32 if jnp.asarray(y0).dtype == jnp.float32 else jnp.float64
    args, order = _fit_args(data, media0, loss_scale, dt)
    layout = _Layout(free, order, exposure, n_lights)
    if weighting == "relative":
        if weights_at is None:
            level = np.abs(np.asarray(args[1]))  # the target, in units of its mean
        else:
            level = np.abs(np.asarray(_model(layout, weights_at, args)))
        args = (*args[:7], jnp.asarray(1.0 / (level + rel_floor), dtype=dt))
    residuals = _residual_fn(layout, loss)
    if solver in ("lm", "gn"):
        slv = (NormalLevenbergMarquardt if solver == "lm" else NormalGaussNewton)(rtol, atol)
        options = {"jac": "fwd"}
    else:
        slv = optx.BFGS(rtol, atol)
        options = {}
    fn = _solver_fn(layout, solver == "bfgs", loss)
    state = _init(slv, fn, y0, args, options)
    y = y0
    loss0 = float(_loss(residuals, y0, args))
    history = [{"step": 0, "loss": loss0, "params": _values(y0, tanh_idx).tolist()}]
    if progress:
        _progress_line(0, loss0, names, _values(y0, tanh_idx))
    result = optx.RESULTS.max_steps_reached
    stalled = False
    n = 0
    for n in range(1, max_steps + 1):
        y, state, done, res, lval = _step(slv, fn, residuals, y, args, options, state)
        lval = float(lval)
        history.append({"step": n, "loss": lval, "params": _values(y, tanh_idx).tolist()})
        if progress:
            _progress_line(n, lval, names, _values(y, tanh_idx))
        if bool(done):
            result = res
            break
        # float32 shading puts a floor under the loss; optimistix's Cauchy test may keep
        # taking rejected LM steps there. Stop once the loss has stalled after progress
        # (or, when starting at the solution, has not moved for 8 steps).
        window = 4 if lval < 0.5 * loss0 else 8
        if n >= window - 1:
            recent = [h["loss"] for h in history[-window:]]
            if max(recent) - min(recent) <= rtol * max(recent):
                result = optx.RESULTS.successful
                stalled = True
                break
    converged = result == optx.RESULTS.successful
    status = (
        "successful"
        if converged
        else ("max_steps_reached" if result == optx.RESULTS.max_steps_reached else "failed")
    )
    message = optx.RESULTS[result] if not converged else "converged"
    if stalled:
        message = "converged (loss unchanged to rtol over the last steps)"
    if not converged and not message:
        message = f"no convergence within {max_steps} steps"
    return dict(
        y=y,
        args=args,
        residuals=residuals,
        order=order,
        steps=n,
        loss0=loss0,
        history=history,
        converged=converged,
        status=status,
        message=message,
    )


def _fit_args(data, media0, loss_scale, dt):
    """The residual functions' `args` for the traces in `data` (independent traces of the
    same target, averaged on the pixels they share): prepared subsurface terms (per light
    group), target and medium-independent radiance (per light group) in units of the
    target's mean level, the media held fixed, the robust-loss scale and unit weights.

    Averaging the traces' models (rather than fitting each trace to the target) is one trace
    with K times the samples: the fit trace's own noise, which a least-squares fit lowers by
    moving toward the coefficients whose image is least noisy (an errors-in-variables bias:
    sharper kernels lean on the per-pixel near field rather than the noisy cloud), falls
    as 1/K instead of staying."""
    if len(data) > 1:
        common = functools.reduce(np.intersect1d, [d["pix"] for d in data])
        sel = []
        for d in data:
            order_p = np.argsort(d["pix"])
            sel.append(order_p[np.searchsorted(d["pix"][order_p], common)])
    else:
        sel = [slice(None)]
    tgt_flat = data[0]["tgt"][sel[0]]
    base = np.mean([d["base"][:, s] for d, s in zip(data, sel, strict=True)], axis=0)
    scale = float(np.mean(np.abs(tgt_flat))) or 1.0  # residuals in units of the mean level
    order = data[0]["materials"]
    groups = range(len(data[0]["sub"]))

    def rows(terms, s):
        return terms if isinstance(s, slice) else terms.rows(jnp.asarray(s))

    # eta is held in a fit: fold its Fresnel factors into the weights once, here
    etas = [media0[m].eta for m in order]
    args = (
        tuple(
            type(data[0]["sub"][g])
            .mean([rows(d["sub"][g], s) for d, s in zip(data, sel, strict=True)])
            .prepare(etas)
            for g in groups
        ),
        jnp.asarray(tgt_flat / scale, dtype=dt),
        data[0]["r_nodes"],
        tuple(media0[m] for m in order),
        scale,
        jnp.asarray(loss_scale, dtype=dt),
        jnp.asarray(base / scale, dtype=dt),
        jnp.ones(tgt_flat.shape, dtype=dt),
    )
    return args, order


def _values(y, tanh_idx) -> np.ndarray:
    """Parameter values from the solver's unconstrained coordinates (float64 NumPy)."""
    y = np.asarray(y, dtype=np.float64)
    return np.where(tanh_idx, np.tanh(y), np.exp(np.where(tanh_idx, 0.0, y)))


def _media_of(free, order, y, media0):
    """Media with the free coefficients set from `y` (3 per free field: log of the
    coefficients, atanh of `g`)."""
    logs = {k: y[3 * i : 3 * i + 3] for i, k in enumerate(free)}
    out = []
    for mat, m in zip(order, media0, strict=True):
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


# The residual and solver functions are cached per parameter layout, and the data travel as
# `args`, so a second fit of the same layout reuses the compiled step.
@dataclasses.dataclass(frozen=True)
class _Layout:
    """What the solver's coordinates mean: 3 per free `(material, field)` (log, or atanh for
    `g`), then the log intensity factor of each free light, then the log exposure."""

    free: tuple
    order: tuple  # the transport's translucent materials
    exposure: bool
    n_lights: int


@eqx.filter_jit
def _model(layout: _Layout, y, args):
    """The fitted pixels' radiance at the solver's coordinates `y`, in units of the target's
    mean: each light group's shading, scaled by its free intensity factor (groups past the
    free lights are held at 1), summed, times the exposure."""
    sub, _, r_nodes, media0, scale, _, base_j, _ = args
    n_c = 3 * len(layout.free)
    media = _media_of(layout.free, layout.order, y[:n_c], media0)
    model = 0.0
    for g, terms in enumerate(sub):
        L = terms.shade(media) / scale + base_j[g]
        model = model + (jnp.exp(y[n_c + g]) * L if g < layout.n_lights else L)
    return jnp.exp(y[-1]) * model if layout.exposure else model


@functools.lru_cache(maxsize=32)
def _residual_fn(layout: _Layout, loss: str = "l2"):
    def residuals(y, args):
        target_j, c, wts = args[1], args[5], args[7]
        r = ((_model(layout, y, args) - target_j) * wts).reshape(-1)
        # robust losses as residual transforms r -> sign(r) sqrt(2 rho(r)): least squares on
        # the transformed residuals minimises sum rho(r)
        if loss == "cauchy":
            return jnp.sign(r) * c * safe_sqrt(jnp.log1p((r / c) ** 2))
        if loss == "huber":
            a = jnp.abs(r)
            return jnp.where(a <= c, r, jnp.sign(r) * safe_sqrt(2 * c * a - c**2))
        return r

    return residuals


@functools.lru_cache(maxsize=32)
def _solver_fn(layout: _Layout, scalar: bool, loss: str = "l2"):
    residuals = _residual_fn(layout, loss)
    if scalar:
        return lambda y, args: (0.5 * jnp.sum(residuals(y, args) ** 2), None)
    return lambda y, args: (residuals(y, args), None)


@eqx.filter_jit
def _loss(residuals, y, args):
    return 0.5 * jnp.sum(residuals(y, args) ** 2)


@eqx.filter_jit
def _jac_res(residuals, y, args):
    return jax.jacfwd(residuals)(y, args), residuals(y, args)


@eqx.filter_jit
def _init(slv, fn, y0, args, options):
    f_struct, aux_struct = jax.eval_shape(lambda: fn(y0, args))
    return slv.init(fn, y0, args, options, f_struct, aux_struct, frozenset())


@eqx.filter_jit
def _step(slv, fn, residuals, y, args, options, state):
    y, state, _ = slv.step(fn, y, args, options, state, frozenset())
    done, res = slv.terminate(fn, y, args, options, state, frozenset())
    # the solver already evaluated the loss at the point it returns (its accepted point)
    return y, state, done, res, state.f_info.as_min()


def _progress_line(step: int, loss: float, names: list[str], vals: np.ndarray) -> None:
    # the material name is dropped (one material in most fits); a light keeps its prefix
    short = [n if n.startswith("lights.") else n.split(".", 1)[-1] for n in names]
    shown = "  ".join(f"{n}={v:.4g}" for n, v in zip(short, vals, strict=True))
    print(f"step {step:3d}  loss {loss:.6g}  {shown}", file=sys.stderr, flush=True)


# --- fit files (`sssjax fit FIT.toml`) -------------------------------------------------
_FIT_KEYS = {"scene", "target", "synthetic", "params", "init", "settings", "solver", "output"}
_SOLVER_KEYS = {
    "method",
    "max_steps",
    "seed",
    "rtol",
    "atol",
    "loss",
    "loss_scale",
    "weighting",
    "rel_floor",
    "traces",
    "refine",
}
_SYNTH_KEYS = {"seed"}


@dataclasses.dataclass
class FitJob:
    """A parsed fit file: everything `fit` needs, plus where results go."""

    path: Path
    scene: Scene
    target: Any  # a path, or None for a synthetic target
    synthetic_seed: int | None
    params: list[str] | None
    init: dict[str, Any]
    method: str
    max_steps: int
    seed: int | None
    rtol: float
    atol: float
    output: Path
    loss: str = "l2"
    loss_scale: float = 0.1
    weighting: str = "absolute"
    rel_floor: float = 0.01
    traces: int = 1
    refine: bool = False

    def fit_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of `fit` this file sets."""
        return dict(
            params=self.params,
            init=self.init,
            seed=self.seed,
            solver=self.method,
            max_steps=self.max_steps,
            rtol=self.rtol,
            atol=self.atol,
            loss=self.loss,
            loss_scale=self.loss_scale,
            weighting=self.weighting,
            rel_floor=self.rel_floor,
            traces=self.traces,
            refine=self.refine,
        )


def load_fit_file(path: str | Path) -> FitJob:
    """Read and validate a fit file (TOML). Relative paths resolve against its folder.

    Keys: `scene` (path), `target` (image path) or `[synthetic] seed = S` (render the target
    from the scene's own media with seed S: a recovery check), `params` (list), `[init]`
    (values in mm^-1 by `MATERIAL.FIELD`), `[settings]` (scene overrides: `width`, `height`,
    `spp`, `light_samples`, `sss_cloud_size`, ...), `[solver]` (`method` lm|gn|bfgs,
    `max_steps`, `seed`, `rtol`, `atol`, `loss` l2|cauchy|huber, `loss_scale`, `weighting`
    absolute|relative, `rel_floor`, `traces`, `refine`), `output` (folder).
    """
    from .scene import did_you_mean, load_scene, read_toml

    path = Path(path)
    d = read_toml(path, FitError, "fit file")

    def unknown(keys, known, where):
        for k in keys:
            if k not in known:
                hint = did_you_mean(k, sorted(known))
                raise FitError(f"{path}: {where}{k}: unknown key{hint}")

    unknown(d, _FIT_KEYS, "")
    if "scene" not in d:
        raise FitError(f"{path}: scene: missing required key")
    if ("target" in d) == ("synthetic" in d):
        raise FitError(f"{path}: give exactly one of 'target' (an image) and [synthetic]")
    base = path.parent
    scene = load_scene(base / d["scene"])
    settings = d.get("settings", {})
    try:
        scene = scene.with_settings(**settings) if settings else scene
    except TypeError as e:
        raise FitError(f"{path}: [settings]: {e}") from None
    solver = d.get("solver", {})
    unknown(solver, _SOLVER_KEYS, "[solver] ")
    synth = d.get("synthetic")
    if synth is not None:
        unknown(synth, _SYNTH_KEYS, "[synthetic] ")
    params = d.get("params")
    if params is not None and (
        not isinstance(params, list) or not all(isinstance(p, str) for p in params)
    ):
        raise FitError(f"{path}: params: expected a list of names like 'marble.sigma_a'")
    return FitJob(
        path=path,
        scene=scene,
        target=(base / d["target"]) if "target" in d else None,
        synthetic_seed=int(synth.get("seed", 1)) if synth is not None else None,
        params=params,
        init=dict(d.get("init", {})),
        method=str(solver.get("method", "lm")),
        max_steps=int(solver.get("max_steps", 50)),
        seed=solver.get("seed"),
        rtol=float(solver.get("rtol", 1e-5)),
        atol=float(solver.get("atol", 1e-6)),
        output=Path(d["output"]) if "output" in d else Path("out") / "fits" / path.stem,
        loss=str(solver.get("loss", "l2")),
        loss_scale=float(solver.get("loss_scale", 0.1)),
        weighting=str(solver.get("weighting", "absolute")),
        rel_floor=float(solver.get("rel_floor", 0.01)),
        traces=int(solver.get("traces", 1)),
        refine=bool(solver.get("refine", False)),
    )
