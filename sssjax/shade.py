"""The differentiable pass: radiance from a `Transport` and the media.

`shade` is smooth in every medium's `sigma_a`, `sigma_s` and `g`: it evaluates the diffusion
profile `R_d` (the scene's `[sss] profile`, carried by the transport; `sssjax.profiles`) on the
transport's distance nodes (a `(B, 3)` table per medium) and contracts it with
the per-pixel gather weights, and it re-weights the stored single-scattering samples by
`integrand / proposal pdf`. No ray is cast here, so a fit can call it every iteration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import jax.numpy as jnp
from jaxtyping import Array, Float

from . import dipole, profiles
from .media import Medium
from .trace import SSSBlock, Transport

__all__ = ["shade", "shade_sss", "shade_image", "media_tuple"]


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
    if profile is None:
        profile = terms.profile
    profiles.check_profile(profile)
    L = jnp.zeros(terms.ss_weight.shape[:1] + (3,), terms.ss_weight.dtype)
    r = r_nodes[:, None]
    for m, med in enumerate(media):
        if multiple:
            rd = profiles.Rd(r, med.sigma_a, med.sigmap_s, med.eta, profile)  # (B, 3)
            L = L + jnp.einsum("cpb,bc->pc", terms.ms_hist[m], rd)
        if single and terms.ss_sp_o.shape[1] > 0:
            f = dipole.single_scatter_integrand(
                terms.ss_sp_o[..., None],
                terms.ss_sp_i[..., None],
                terms.ss_cos_i[..., None],
                terms.ss_cos_o[..., None],
                terms.ss_cos_phase[..., None],
                med.sigma_s,
                med.sigma_t,
                med.g,
                med.eta,
            )
            sel = (terms.ss_mat == m)[..., None]
            contrib = jnp.where(sel, f * terms.ss_weight / terms.ss_pdf[..., None], 0.0)
            L = L + jnp.sum(contrib, axis=1)
    return L


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
