"""The diffusion transport (Jensen et al. 2001): a diffusion profile gathered from an
irradiance cloud plus explicit single scattering, at the first translucent hit of each
camera sample's specular chain.

Two phases: the chains (`chains.py`) run on every pixel; the subsurface terms, the
expensive part, only on the pixels that see a translucent object, packed into full blocks by
the renderer: the profile gather on distance nodes (`gather.py`, from the irradiance cloud
of `cloud.py` or per-pixel Monte Carlo samples) and single scattering (`single.py`).

`DiffusionTerms` are the trace's media-dependent terms; `prepare` folds the Fresnel factors
and proposal pdfs of single scattering in (`DiffusionShading`), whose `shade` evaluates the
profile on the nodes and re-weights the single-scattering records, channel-major, so that
forward-mode tangents of a fit batch into matrix products.

Approximations: direct lighting of translucent objects (lights only, with shadows),
opaque shadows of translucent objects, subsurface light at the first translucent hit only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .. import profiles
from .._arrays import SceneArrays
from ..dipole import single_scatter_kernel
from ..scattering import fresnel_transmittance
from ._base import Block, Prepared, Terms, TransportMethod
from ._record import NO_RECORD, Recorder
from ._strategies import STRATEGIES
from .chains import chain_block
from .cloud import irradiance_cloud
from .gather import Nodes, gather_beams, gather_cloud, gather_samples
from .single import no_records, records_per_sample, single_scatter

__all__ = ["Diffusion", "DiffusionTerms", "DiffusionShading"]

_SS = ("ss_mat", "ss_sp_o", "ss_sp_i", "ss_cos_i", "ss_cos_o", "ss_cos_phase", "ss_pdf")


class DiffusionTerms(Terms):
    """The subsurface terms of `Pt` pixel rows: profile gather weights on the distance
    nodes and `K` single-scattering records per row. Radiometric values are pixel means."""

    # channel-major, so that shading is one batched matrix-vector product per material
    # (10x faster on CPU than a trailing channel axis)
    ms_hist: Float[Array, "Mt 3 Pt B"]
    ss_mat: Int[Array, "Pt K"]  # material of each record (-1: none)
    ss_sp_o: Float[Array, "Pt K"]  # depth of the scatter point along the refracted view ray
    ss_sp_i: Float[Array, "Pt K"]  # refracted distance to the exit point towards the light
    ss_cos_i: Float[Array, "Pt K"]
    ss_cos_o: Float[Array, "Pt K"]
    ss_cos_phase: Float[Array, "Pt K"]
    ss_pdf: Float[Array, "Pt K"]  # proposal pdf of `ss_sp_o`, mm^-1
    ss_weight: Float[Array, "Pt K 3"]  # light carried to the pixel, x the pixel share
    r_nodes: Float[Array, " B"]  # the distance nodes, mm
    profile: str = eqx.field(static=True, default="dipole")  # `[sss] profile`

    def rows(self, idx) -> DiffusionTerms:
        return eqx.tree_at(
            lambda t: (t.ms_hist, *(getattr(t, f) for f in _SS), t.ss_weight),
            self,
            (self.ms_hist[:, :, idx], *(getattr(self, f)[idx] for f in _SS), self.ss_weight[idx]),
        )

    @classmethod
    def concat(cls, parts: Sequence[DiffusionTerms]) -> DiffusionTerms:
        host = all(isinstance(p.ms_hist, np.ndarray) for p in parts)
        cat = np.concatenate if host else jnp.concatenate
        return _combine(parts, lambda h: cat(h, axis=2), axis=0, weight=1.0)

    @classmethod
    def mean(cls, parts: Sequence[DiffusionTerms]) -> DiffusionTerms:
        """The histograms averaged, the single-scattering records pooled at `1 / len(parts)`
        of their weight."""
        k = len(parts)
        if k == 1:
            return parts[0]
        return _combine(parts, lambda h: sum(h) / k, axis=1, weight=1.0 / k)

    def prepare(self, etas: Sequence) -> DiffusionShading:
        mat = self.ss_mat
        eta = jnp.asarray([jnp.asarray(e) for e in etas] or [1.0])[jnp.clip(mat, 0, None)]
        F = fresnel_transmittance(self.ss_cos_i, eta) * fresnel_transmittance(self.ss_cos_o, eta)
        w = jnp.where((mat >= 0)[..., None], self.ss_weight * (F / self.ss_pdf)[..., None], 0.0)
        return DiffusionShading(
            self.ms_hist,
            mat,
            self.ss_sp_i + self.ss_sp_o,
            self.ss_cos_phase,
            jnp.moveaxis(w, -1, 0),
            self.r_nodes,
            self.profile,
        )


def _combine(parts, hist, axis: int, weight: float) -> DiffusionTerms:
    """Terms of `parts` with histograms combined by `hist` and the records concatenated
    along `axis` (0: rows, 1: records), their weights times `weight` (NumPy for parts on the
    host, as the renderer assembles them: no compiled concatenation per trace)."""
    host = all(isinstance(p.ms_hist, np.ndarray) for p in parts)
    cat = np.concatenate if host else jnp.concatenate
    p0 = parts[0]
    return DiffusionTerms(
        hist([p.ms_hist for p in parts]),
        *(cat([getattr(p, f) for p in parts], axis=axis) for f in _SS),
        cat([p.ss_weight for p in parts], axis=axis) * weight,
        p0.r_nodes,
        p0.profile,
    )


class DiffusionShading(Prepared):
    """Prepared diffusion terms: what `sigma_a`, `sigma_s`, `g` act on, everything fixed by
    the geometry and `eta` (single scattering's Fresnel factors and proposal pdf) folded into
    the record weights."""

    ms_hist: Float[Array, "Mt 3 Pt B"]  # profile gather weights on the distance nodes
    ss_mat: Int[Array, "Pt K"]  # material of each single-scattering record (-1: none)
    ss_length: Float[Array, "Pt K"]  # s'_i + s'_o, mm
    ss_cos_phase: Float[Array, "Pt K"]
    ss_weight: Float[Array, "3 Pt K"]  # record weight x F_t(w_i) F_t(w_o) / pdf, channel-major
    r_nodes: Float[Array, " B"]  # the distance nodes, mm
    profile: str = eqx.field(static=True, default="dipole")

    def shade(
        self,
        media: Sequence,
        *,
        multiple: bool = True,
        single: bool = True,
        profile: str | None = None,
    ) -> Float[Array, "Pt 3"]:
        """Subsurface radiance for `media` (coefficients in mm^-1; their `eta` enters the
        diffusion profile, the one `prepare` was given the rest): the profile (`profile`,
        default the scene's) on the nodes contracted with the gather weights, plus the
        re-weighted single-scattering records."""
        profile = profiles.check_profile(self.profile if profile is None else profile)
        # channel-major throughout (`(3, P)`): the forward-mode Jacobian of a fit then batches
        # its tangents into matrix products instead of transposing the histogram (5x faster)
        L = jnp.zeros(self.ss_weight.shape[:2], self.ss_weight.dtype)
        r = self.r_nodes[:, None]
        for m, med in enumerate(media):
            if multiple:
                rd = profiles.Rd(r, med.sigma_a, med.sigmap_s, med.eta, profile)  # (B, 3)
                L = L + jnp.einsum("cpb,cb->cp", self.ms_hist[m], rd.T)
            if single and self.ss_length.shape[1] > 0:
                coef = [jnp.broadcast_to(x, (3,)) for x in (med.sigma_s, med.sigma_t, med.g)]
                rows = []
                for c in range(3):
                    k = single_scatter_kernel(
                        self.ss_length, self.ss_cos_phase, coef[0][c], coef[1][c], coef[2][c]
                    )
                    f = self.ss_weight[c] * k  # zero weight where no material
                    if len(media) > 1:
                        f = jnp.where(self.ss_mat == m, f, 0.0)
                    rows.append(jnp.sum(f, axis=1))
                L = L + jnp.stack(rows)
        return L.T


class Diffusion(TransportMethod):
    """The diffusion transport of one scene (its static configuration: cloud and beam
    sizes rounded up to a multiple of spp, the distance nodes, what is on)."""

    name = "diffusion"
    two_phase = True

    def __init__(self, arrays: SceneArrays):
        sss, spp = arrays.sss, arrays.render.spp
        self.cloud_n = int(math.ceil(sss.cloud_size / spp) * spp)
        self.beam_n = int(math.ceil(sss.beam_points / spp) * spp)  # rays per beam light
        self.nodes = Nodes.of(arrays, self.cloud_n)
        self.subsurface = sss.enabled and arrays.n_objects > 0
        self.ss_per_sample = (
            records_per_sample(arrays) if self.subsurface and sss.single_scattering else 0
        )
        self.strategy = STRATEGIES[sss.strategy]
        self.materials = arrays.materials
        self.profile = sss.profile

    @property
    def media_dependent(self) -> bool:
        return self.subsurface

    def empty_terms(self) -> DiffusionTerms:
        Mt, B, K = len(self.materials), self.nodes.bins, self.ss_per_sample
        return DiffusionTerms(
            jnp.zeros((Mt, 3, 0, B)),
            jnp.zeros((0, K), jnp.int32),
            *(jnp.zeros((0, K)) for _ in _SS[1:]),
            jnp.zeros((0, K, 3)),
            jnp.asarray(self.nodes.r_nodes, dtype=float),
            self.profile,
        )

    def image_state(self, arrays: SceneArrays, key):
        """The irradiance cloud (`None` without subsurface scattering)."""
        if not self.subsurface:
            return None
        return irradiance_cloud(
            arrays, jax.random.fold_in(key, 0x5C0FFEE), self.cloud_n, self.beam_n
        )

    def trace_block(self, arrays, state, pixels, key, rec: Recorder = NO_RECORD) -> Block:
        """Phase 1: the camera chains. `Block.rows` are the per-sample slots of each pixel's
        first translucent hits; `needs` the pixels with one."""
        base, slots = chain_block(arrays, pixels, key, subsurface=self.subsurface, rec=rec)
        return Block(base, jnp.any(slots["have"], axis=1), slots)

    def trace_rows(self, arrays, cloud, slots, valid, key, rec: Recorder = NO_RECORD):
        """Phase 2: the subsurface terms of packed pixels (`slots` `(P, spp, ...)`)."""
        P, S = slots["have"].shape
        s = {f: v.reshape(P * S, *v.shape[2:]) for f, v in slots.items()}
        s["have"] = s["have"] & jnp.repeat(valid, S)
        k_ms, key = jax.random.split(key)
        if self.strategy.per_pixel:
            hist = gather_samples(arrays, self.nodes, self.strategy, k_ms, s, P, S, rec)
        else:
            hist = gather_cloud(arrays, self.nodes, cloud, s, P, S, rec)
        if arrays.light_base.n_beam:
            hist = hist + gather_beams(arrays, self.nodes, cloud, s, P, S, rec)
        if self.ss_per_sample > 0:
            ss = single_scatter(arrays, key, s, P, S, rec)
        else:
            ss = no_records(P)
        return DiffusionTerms(
            ms_hist=jnp.transpose(hist, (0, 3, 1, 2)),
            ss_mat=ss["mat"],
            ss_sp_o=ss["sp_o"],
            ss_sp_i=ss["sp_i"],
            ss_cos_i=ss["cos_i"],
            ss_cos_o=ss["cos_o"],
            ss_cos_phase=ss["phase"],
            ss_pdf=ss["pdf"],
            ss_weight=ss["weight"],
            r_nodes=jnp.asarray(self.nodes.r_nodes, dtype=float),
            profile=self.profile,
        )
