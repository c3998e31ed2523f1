"""The differentiable pass: radiance from a `Transport` and the media.

`shade` is smooth in every medium's `sigma_a`, `sigma_s` and `g`: it evaluates the diffusion
profile `R_d` (the scene's `[sss] profile`, carried by the transport; `sssjax.profiles`) on the
transport's distance nodes (a `(B, 3)` table per medium) and contracts it with
the per-pixel gather weights, and it re-weights the stored single-scattering samples by
`integrand / proposal pdf`. No ray is cast here, so a fit can call it every iteration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from . import dipole, profiles
from .media import Medium
from .trace import SSSBlock, Transport

__all__ = [
    "shade",
    "shade_sss",
    "shade_image",
    "media_tuple",
    "ShadingTerms",
    "prepare",
    "shade_prepared",
]


def media_tuple(transport: Transport, media: Mapping[str, Medium] | Sequence[Medium]):
    """Order `media` (a dict by material name, or a sequence) as the transport expects."""
    if isinstance(media, Mapping):
        missing = [n for n in transport.materials if n not in media]
        if missing:
            raise ValueError(f"shade: no medium given for translucent material(s) {missing}")
        return tuple(media[n] for n in transport.materials)
    media = tuple(media)
    if len(media) != len(transport.materials):
        raise ValueError(
            f"shade: expected {len(transport.materials)} media "
            f"({', '.join(transport.materials)}), got {len(media)}"
        )
    return media


class ShadingTerms(eqx.Module):
    """The subsurface terms of a block of pixels, reduced to what `sigma_a`, `sigma_s`, `g`
    act on: everything fixed by the geometry and `eta` (the Fresnel factors of single
    scattering and its proposal pdf) folded into the sample weights.

    `prepare` makes them once per trace; `shade_prepared` evaluates them for any media. A fit
    holds `eta`, so it prepares once and re-shades every iteration.
    """

    ms_hist: Float[Array, "Mt 3 P B"]  # profile gather weights on the distance nodes
    ss_mat: Int[Array, "P K"]  # material of each single-scattering record (-1: none)
    ss_length: Float[Array, "P K"]  # s'_i + s'_o, mm
    ss_cos_phase: Float[Array, "P K"]
    ss_weight: Float[Array, "3 P K"]  # record weight x F_t(w_i) F_t(w_o) / pdf, channel-major
    profile: str = eqx.field(static=True, default="dipole")

    def rows(self, rows) -> ShadingTerms:
        """The terms of pixel rows `rows` (an index array)."""
        return ShadingTerms(
            self.ms_hist[:, :, rows],
            self.ss_mat[rows],
            self.ss_length[rows],
            self.ss_cos_phase[rows],
            self.ss_weight[:, rows],
            self.profile,
        )

    @staticmethod
    def mean(parts: Sequence[ShadingTerms]) -> ShadingTerms:
        """The terms of independent traces of the same pixels, averaged: one trace with
        `len(parts)` times the samples (the histograms averaged, the single-scattering
        records pooled at `1 / len(parts)` of their weight)."""
        cat, k = jnp.concatenate, len(parts)
        if k == 1:
            return parts[0]
        return ShadingTerms(
            sum(p.ms_hist for p in parts) / k,
            cat([p.ss_mat for p in parts], axis=1),
            cat([p.ss_length for p in parts], axis=1),
            cat([p.ss_cos_phase for p in parts], axis=1),
            cat([p.ss_weight for p in parts], axis=2) / k,
            parts[0].profile,
        )


def prepare(terms: Transport | SSSBlock, etas: Sequence) -> ShadingTerms:
    """Fold the `eta`-dependent factors of `terms` into its weights (`etas`: one refractive
    index per translucent material, in the transport's order)."""
    mat = terms.ss_mat
    eta = jnp.asarray([jnp.asarray(e) for e in etas] or [1.0])[jnp.clip(mat, 0, None)]
    F = dipole.fresnel_transmittance(terms.ss_cos_i, eta)
    F = F * dipole.fresnel_transmittance(terms.ss_cos_o, eta)
    w = jnp.where((mat >= 0)[..., None], terms.ss_weight * (F / terms.ss_pdf)[..., None], 0.0)
    return ShadingTerms(
        terms.ms_hist,
        mat,
        terms.ss_sp_i + terms.ss_sp_o,
        terms.ss_cos_phase,
        jnp.moveaxis(w, -1, 0),
        terms.profile,
    )


def shade_prepared(
    terms: ShadingTerms,
    media: Sequence[Medium],
    r_nodes: Array,
    *,
    multiple: bool = True,
    single: bool = True,
    profile: str | None = None,
) -> Float[Array, "P 3"]:
    """Subsurface radiance of prepared terms (`prepare`) for `media` (coefficients in mm^-1;
    their `eta` enters the diffusion profile, the one `prepare` was given the rest)."""
    if profile is None:
        profile = terms.profile
    profiles.check_profile(profile)
    # channel-major throughout (`(3, P)`): the forward-mode Jacobian of a fit then batches
    # its tangents into matrix products instead of transposing the histogram (5x faster)
    L = jnp.zeros(terms.ss_weight.shape[:2], terms.ss_weight.dtype)
    r = r_nodes[:, None]
    for m, med in enumerate(media):
        if multiple:
            rd = profiles.Rd(r, med.sigma_a, med.sigmap_s, med.eta, profile)  # (B, 3)
            L = L + jnp.einsum("cpb,cb->cp", terms.ms_hist[m], rd.T)
        if single and terms.ss_length.shape[1] > 0:
            coef = [jnp.broadcast_to(x, (3,)) for x in (med.sigma_s, med.sigma_t, med.g)]
            rows = []
            for c in range(3):
                k = dipole.single_scatter_kernel(
                    terms.ss_length, terms.ss_cos_phase, coef[0][c], coef[1][c], coef[2][c]
                )
                f = terms.ss_weight[c] * k  # zero weight where no material
                if len(media) > 1:
                    f = jnp.where(terms.ss_mat == m, f, 0.0)
                rows.append(jnp.sum(f, axis=1))
            L = L + jnp.stack(rows)
    return L.T


def shade_sss(
    terms: Transport | SSSBlock,
    media: Sequence[Medium],
    r_nodes: Array,
    *,
    multiple: bool = True,
    single: bool = True,
    profile: str | None = None,
) -> Float[Array, "Pt 3"]:
    """Subsurface radiance of the translucent rows: profile gather plus single scattering.

    `profile` (one of `sssjax.profiles.PROFILES`) defaults to `terms.profile`, the scene's
    `[sss] profile` that `trace` recorded (an `SSSBlock` from `Transport.sss_terms` keeps it)."""
    prep = prepare(terms, [m.eta for m in media])
    return shade_prepared(prep, media, r_nodes, multiple=multiple, single=single, profile=profile)


def shade(
    transport: Transport,
    media: Mapping[str, Medium] | Sequence[Medium],
    *,
    multiple: bool = True,
    single: bool = True,
) -> Float[Array, "P 3"]:
    """Radiance of the transport's pixels for the given media.

    **Arguments:**

    - `transport`: from `trace`.
    - `media`: one `Medium` per translucent material: a dict by material name (as
      `scene.media()` returns) or a sequence in `transport.materials` order. Coefficients
      in mm^-1.
    - `multiple`, `single`: include the multiple-scattering (diffusion profile) and
      single-scattering terms. The profile is `transport.profile` (the scene's).

    **Returns:** `(P, 3)` linear RGB radiance, one row per `transport.pixels` entry.
    """
    media = media_tuple(transport, media)
    sss = shade_sss(transport, media, transport.r_nodes, multiple=multiple, single=single)
    return transport.base.at[transport.t_rows].add(sss)


def shade_image(transport: Transport, media, **kw) -> Float[Array, "H W 3"]:
    """`shade` scattered back into a full `(height, width, 3)` image (zeros elsewhere)."""
    L = shade(transport, media, **kw)
    img = jnp.zeros((transport.height * transport.width, 3), L.dtype)
    img = img.at[transport.pixels].set(L)
    return img.reshape(transport.height, transport.width, 3)
