"""The differentiable pass: radiance from a `Transport` and the media.

`shade` is smooth in every medium's `sigma_a`, `sigma_s` and `g`: it adds the transport's
media-dependent terms, shaded for the media (`Terms.shade`, e.g. the diffusion profile on
distance nodes and re-weighted single scattering), to the media-independent `base`. No ray
is cast here, so a fit can call it every iteration. Whatever transport traced the terms,
shading goes through the same protocol (`sssjax.transport.Terms`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import jax.numpy as jnp
from jaxtyping import Array, Float

from .media import Medium
from .transport import Prepared, Terms, Transport

__all__ = ["shade", "shade_sss", "shade_image", "media_tuple", "prepare", "shade_prepared"]


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


def prepare(terms: Transport | Terms, etas: Sequence) -> Prepared:
    """`Terms.prepare`: fold the `eta`-dependent factors into the terms (`etas`: one
    refractive index per translucent material, in the transport's order)."""
    return _terms(terms).prepare(etas)


def shade_prepared(
    terms: Prepared, media: Sequence[Medium], r_nodes: Array | None = None, **options
) -> Float[Array, "Pt 3"]:
    """`Prepared.shade`: radiance of prepared terms (`prepare`) for `media` (coefficients
    in mm^-1). `r_nodes` is accepted for compatibility (the terms carry their nodes)."""
    return terms.shade(media, **options)


def shade_sss(
    terms: Transport | Terms, media: Sequence[Medium], r_nodes: Array | None = None, **options
) -> Float[Array, "Pt 3"]:
    """The media-dependent radiance of the rows with terms (`Transport.t_rows`).

    `options` go to the terms' `shade` (diffusion: `multiple=`, `single=`, `profile=`, one of
    `sssjax.profiles.PROFILES`, default the scene's `[sss] profile` that `trace` recorded).
    `r_nodes` is accepted for compatibility (the terms carry their nodes)."""
    return _terms(terms).shade(media, **options)


def _terms(t: Transport | Terms) -> Terms:
    return t.terms if isinstance(t, Transport) else t


def shade(
    transport: Transport, media: Mapping[str, Medium] | Sequence[Medium], **options
) -> Float[Array, "P 3"]:
    """Radiance of the transport's pixels for the given media.

    **Arguments:**

    - `transport`: from `trace`.
    - `media`: one `Medium` per translucent material: a dict by material name (as
      `scene.media()` returns) or a sequence in `transport.materials` order. Coefficients
      in mm^-1.
    - `options`: for the diffusion transport, `multiple=`, `single=` (bool): include the
      multiple-scattering (diffusion profile, the scene's) and single-scattering terms.

    **Returns:** `(P, 3)` linear RGB radiance, one row per `transport.pixels` entry.
    """
    media = media_tuple(transport, media)
    L = transport.terms.shade(media, **options)
    return transport.base.at[transport.t_rows].add(L)


def shade_image(transport: Transport, media, **kw) -> Float[Array, "H W 3"]:
    """`shade` scattered back into a full `(height, width, 3)` image (zeros elsewhere)."""
    L = shade(transport, media, **kw)
    img = jnp.zeros((transport.height * transport.width, 3), L.dtype)
    img = img.at[transport.pixels].set(L)
    return img.reshape(transport.height, transport.width, 3)
