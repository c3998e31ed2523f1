"""Homogeneous scattering media: coefficients, derived quantities and measured presets.

All coefficients are in **per millimetre** (mm^-1); all lengths in **millimetres**.
Colour is linear RGB: every coefficient is a length-3 array (a scalar is broadcast).
"""

from __future__ import annotations

import difflib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._numerics import float_dtype, safe_div, safe_sqrt

__all__ = ["Medium", "PRESETS", "preset", "preset_names"]


def _as_rgb(x: ArrayLike) -> Array:
    x = jnp.asarray(x, dtype=float_dtype()) if not isinstance(x, jax.core.Tracer) else x
    if x.ndim == 0:
        x = jnp.broadcast_to(x, (3,))
    return x


def _as_scalar(x: ArrayLike) -> Array:
    if isinstance(x, jax.core.Tracer):
        return x
    return jnp.asarray(x, dtype=float_dtype())


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _fmt(x) -> str:
    a = np.asarray(x)
    return f"{a.item():g}" if a.ndim == 0 else "[" + ", ".join(f"{v:g}" for v in a.ravel()) + "]"


class Medium(eqx.Module):
    """A homogeneous participating medium behind a smooth dielectric boundary.

    An immutable pytree: `jax.grad`, `jax.jacfwd` and `jax.vmap` act on its four leaves.

    **Arguments:**

    - `sigma_a`: absorption coefficient, RGB, mm^-1, `>= 0`.
    - `sigma_s`: scattering coefficient, RGB, mm^-1, `>= 0`.
    - `g`: Henyey-Greenstein mean cosine, scalar or RGB, `|g| < 1`.
    - `eta`: relative index of refraction of the medium (inside / outside), `> 0`.

    Concrete user input is validated at construction (a `ValueError` names the field and
    the value); traced values inside `jit` are not checked.
    """

    sigma_a: Float[Array, "3"] = eqx.field(converter=_as_rgb)
    sigma_s: Float[Array, "3"] = eqx.field(converter=_as_rgb)
    g: Float[Array, "*c"] = eqx.field(converter=_as_scalar, default=0.0)
    eta: Float[Array, ""] = eqx.field(converter=_as_scalar, default=1.3)

    def __check_init__(self):
        for name in ("sigma_a", "sigma_s"):
            v = getattr(self, name)
            if not _is_concrete(v):
                continue
            if v.shape != (3,):
                raise ValueError(
                    f"Medium.{name} must be a scalar or an RGB triple, got shape {v.shape}"
                )
            a = np.asarray(v)
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Medium.{name} must be finite, got {_fmt(a)} (mm^-1)")
            if np.any(a < 0):
                raise ValueError(f"Medium.{name} must be >= 0, got {_fmt(a)} (mm^-1)")
        if _is_concrete(self.g):
            g = np.asarray(self.g)
            if g.shape not in ((), (3,)):
                raise ValueError(f"Medium.g must be a scalar or an RGB triple, got shape {g.shape}")
            if not np.all(np.isfinite(g)) or np.any(np.abs(g) >= 1):
                raise ValueError(f"Medium.g must satisfy |g| < 1, got {_fmt(g)}")
        if _is_concrete(self.eta):
            eta = np.asarray(self.eta)
            if eta.shape != ():
                raise ValueError(f"Medium.eta must be a scalar, got shape {eta.shape}")
            if not np.isfinite(eta) or eta <= 0:
                raise ValueError(f"Medium.eta must be finite and > 0, got {_fmt(eta)}")

    # -- constructors -------------------------------------------------------------------
    @classmethod
    def from_reduced(
        cls, sigma_a: ArrayLike, sigmap_s: ArrayLike, g: ArrayLike = 0.0, eta: ArrayLike = 1.3
    ) -> Medium:
        """Build from the *reduced* scattering coefficient `sigmap_s = sigma_s (1 - g)`.

        **Arguments:** `sigma_a`, `sigmap_s` in mm^-1 (RGB), `g`, `eta` as in `Medium`.

        **Returns:** a `Medium` with `sigma_s = sigmap_s / (1 - g)`.
        """
        g_arr = jnp.asarray(g, dtype=float_dtype())
        if _is_concrete(g_arr) and np.any(np.abs(np.asarray(g_arr)) >= 1):
            raise ValueError(f"Medium.g must satisfy |g| < 1, got {_fmt(g_arr)}")
        return cls(sigma_a, jnp.asarray(sigmap_s) / (1.0 - g_arr), g, eta)

    @classmethod
    def preset(cls, name: str) -> Medium:
        """A measured material of Jensen et al. 2001 by (case-insensitive) name."""
        return preset(name)

    # -- derived quantities (book notation) --------------------------------------------
    @property
    def sigma_t(self) -> Array:
        """Extinction coefficient `sigma_a + sigma_s`, mm^-1."""
        return self.sigma_a + self.sigma_s

    @property
    def sigmap_s(self) -> Array:
        """Reduced scattering coefficient `sigma_s (1 - g)`, mm^-1."""
        return self.sigma_s * (1.0 - self.g)

    @property
    def sigmap_t(self) -> Array:
        """Reduced extinction coefficient `sigma_a + sigmap_s`, mm^-1."""
        return self.sigma_a + self.sigmap_s

    @property
    def albedo(self) -> Array:
        """Single-scattering albedo `sigma_s / sigma_t` (0 where `sigma_t = 0`)."""
        return safe_div(self.sigma_s, self.sigma_t)

    @property
    def alpha_p(self) -> Array:
        """Reduced albedo `sigmap_s / sigmap_t` (0 where `sigmap_t = 0`)."""
        return safe_div(self.sigmap_s, self.sigmap_t)

    @property
    def sigma_tr(self) -> Array:
        """Effective transport coefficient `sqrt(3 sigma_a sigmap_t)`, mm^-1."""
        return safe_sqrt(3.0 * self.sigma_a * self.sigmap_t)

    @property
    def mean_free_path(self) -> Array:
        """Mean free path `1 / sigma_t`, mm (inf where `sigma_t = 0`)."""
        return safe_div(1.0, self.sigma_t, jnp.inf)

    @property
    def reduced_mean_free_path(self) -> Array:
        """Reduced mean free path `l_u = 1 / sigmap_t` (Jensen's `l_u`, the real-source depth `z_r`), mm."""
        return safe_div(1.0, self.sigmap_t, jnp.inf)

    @property
    def diffuse_mean_free_path(self) -> Array:
        """Diffuse mean free path (diffusion length) `1 / sigma_tr`, mm (inf where `sigma_a = 0`)."""
        return safe_div(1.0, self.sigma_tr, jnp.inf)

    def scaled(self, scale: ArrayLike) -> Medium:
        """Both coefficients multiplied by `scale` (RGB or scalar): the same material at another unit size."""
        return Medium(self.sigma_a * scale, self.sigma_s * scale, self.g, self.eta)

    def __repr__(self) -> str:
        return (
            f"Medium(sigma_a={_fmt(self.sigma_a)}, sigma_s={_fmt(self.sigma_s)}, "
            f"g={_fmt(self.g)}, eta={_fmt(self.eta)})"
        )


# Jensen, Marschner, Levoy, Hanrahan 2001, Figure 5: sigmap_s and sigma_a in mm^-1 (RGB),
# measured with g = 0 and eta = 1.3.
PRESETS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "chicken1": ((0.15, 0.21, 0.38), (0.015, 0.077, 0.19)),
    "chicken2": ((0.19, 0.25, 0.32), (0.018, 0.088, 0.20)),
    "cream": ((7.38, 5.47, 3.15), (0.0002, 0.0028, 0.0163)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12)),
    "skimmilk": ((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145)),
    "wholemilk": ((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014)),
}
PRESET_ETA = 1.3


def preset_names() -> list[str]:
    """The names of the measured presets, sorted."""
    return sorted(PRESETS)


def preset(name: str) -> Medium:
    """A measured material of Jensen et al. 2001 (`g = 0`, `eta = 1.3`).

    **Arguments:** `name`, case-insensitive (e.g. `"Marble"`, `"skimmilk"`).

    **Returns:** the `Medium`. An unknown name raises `ValueError` listing the known ones.
    """
    key = str(name).strip().lower()
    if key not in PRESETS:
        close = difflib.get_close_matches(key, PRESETS, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ValueError(
            f"unknown preset '{name}'{hint}; known presets: {', '.join(preset_names())}"
        )
    sigmap_s, sigma_a = PRESETS[key]
    return Medium.from_reduced(sigma_a, sigmap_s, g=0.0, eta=PRESET_ETA)
