"""The transport interface: what a transport traces, and the protocol its terms follow.

A transport (`TransportMethod`, one per scene, looked up in `TRANSPORTS` by the scene's
`[sss] transport`) is static configuration plus pure functions of the scene's arrays
(`sssjax.SceneArrays`), pixels and a random key. For a block of pixels it returns their
media-independent radiance `base (P, 3)` and, for the rows whose radiance depends on the
media (`needs`), its `Terms`: everything `shade` needs to turn media into radiance, with no
ray left to cast. `sssjax.render` owns tiles, devices, sharding, packing and progress and
calls the transport; `shade` and `fit` use the terms only through the `Terms` / `Prepared`
protocol below, so they do not know which transport produced them.

Two shapes of transport fit:

- one phase (e.g. a volumetric path tracer): `trace_block` returns the terms of every row
  of the block (`Block.rows` is a `Terms`), the renderer keeps the rows that need them;
- two phases (`two_phase = True`, the diffusion transport): `trace_block` returns a cheap
  per-row state (`Block.rows`, any pytree with a leading row axis), and the renderer packs the
  rows that `need` media-dependent work into full blocks for `trace_rows`, so the expensive
  part runs on those rows only.

`image_state` is computed once per image and shared by every block (the diffusion
transport's irradiance cloud).
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from ._record import NO_RECORD, Recorder

__all__ = ["Terms", "Prepared", "Transport", "Block", "TransportMethod"]


class Prepared(eqx.Module):
    """Terms with everything fixed by the geometry and `eta` folded in (`Terms.prepare`):
    what a fit evaluates every iteration."""

    def halves(self) -> tuple[Prepared, Prepared] | None:
        """Re-weighting transports: the terms split into two statistically independent
        halves (disjoint walks), each an estimate of the whole (twice its share), so that a
        fit can take its residuals from one and its derivatives from the other; None where
        the terms are not samples (or cannot be split)."""
        return None

    @abc.abstractmethod
    def shade(self, media: Sequence, **options) -> Float[Array, "Pt 3"]:
        """Radiance of the rows for `media` (one `Medium` per translucent material, in the
        transport's order; coefficients in mm^-1). Smooth in the coefficients."""


class Terms(eqx.Module):
    """The media-dependent part of a trace for `Pt` pixel rows (a pytree).

    The protocol `render`, `shade` and `fit` use: `rows`, `concat`, `mean`, `prepare` and
    `Prepared.shade`; `shade` here is `prepare` then `Prepared.shade`.
    """

    @abc.abstractmethod
    def rows(self, idx: Int[Array, " R"]) -> Terms:
        """The terms of rows `idx` (an index array, NumPy or JAX)."""

    @classmethod
    @abc.abstractmethod
    def concat(cls, parts: Sequence[Terms]) -> Terms:
        """The rows of `parts` one after the other (the blocks of one trace)."""

    @classmethod
    @abc.abstractmethod
    def mean(cls, parts: Sequence[Terms]) -> Terms:
        """Independent traces of the same rows, averaged: one trace with `len(parts)` times
        the samples (the image is linear in the terms)."""

    @abc.abstractmethod
    def prepare(self, etas: Sequence) -> Prepared:
        """Fold what depends only on the geometry and the refractive indices `etas` (one per
        translucent material, in the transport's order) into the terms, once."""

    def sample_efficiency(self, media: Sequence) -> Float[Array, "Pt 3"] | None:
        """Re-weighting transports: per row and channel, the effective sample size of the
        terms shaded at `media` over its value at the proposal (1 at the proposal, falling
        as the media move away). None for transports whose terms are exact in the media."""
        return None

    def shade(self, media: Sequence, **options) -> Float[Array, "Pt 3"]:
        """`prepare` at the media's `eta`, then `Prepared.shade`."""
        return self.prepare([m.eta for m in media]).shade(media, **options)


class Transport(eqx.Module):
    """The media-independent result of `trace` for a set of pixels.

    `base` holds everything that does not involve a medium. The media-dependent `terms`
    exist only for the rows `t_rows` of the pixels whose radiance depends on the media. All
    radiometric fields are pixel averages (divided by spp); `materials` names the
    translucent materials in the order `shade` takes media.
    """

    pixels: Int[Array, " P"]
    base: Float[Array, "P 3"]
    t_rows: Int[Array, " Pt"]
    terms: Terms
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    materials: tuple = eqx.field(static=True)

    @property
    def num_pixels(self) -> int:
        return self.pixels.shape[0]

    def translucent_pixels(self) -> Array:
        """Flat pixel indices of the rows with media-dependent terms."""
        return self.pixels[self.t_rows]

    def sss_terms(self) -> Terms:
        """The media-dependent terms (rows `t_rows`)."""
        return self.terms

    def __getattr__(self, name: str) -> Any:
        # the diffusion terms' fields read as the transport's own (`transport.ms_hist`,
        # `transport.r_nodes`, `transport.profile`), as before the terms had their own class
        if name.startswith("_"):
            raise AttributeError(name)
        terms = self.__dict__.get("terms")
        if terms is not None and hasattr(terms, name):
            return getattr(terms, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


class Block(NamedTuple):
    """What `TransportMethod.trace_block` returns for `P` pixels."""

    base: Float[Array, "P 3"]  # media-independent radiance (pixel means)
    needs: Bool[Array, " P"]  # the rows whose radiance depends on the media
    rows: Any  # per-row pytree (leading axis P): a `Terms`, or a two-phase transport's state


class TransportMethod(abc.ABC):
    """One scene's light transport: built once from its `SceneArrays` (static settings
    only: nothing here changes when `eta` or a light's gain does), used through pure
    functions of `(arrays, ..., key)`. Every function takes a `rec` recorder
    (`sssjax.transport.NO_RECORD` by default) and calls its hooks where rays are cast."""

    name: ClassVar[str]
    two_phase: ClassVar[bool] = False
    # True: the terms are samples drawn with the arrays' media (the proposal) and re-weighted
    # exactly to any media; a fit re-traces at its solution so the proposal matches (lower
    # variance), and `g` (not re-weighted) cannot be fitted
    reweighted: ClassVar[bool] = False

    @abc.abstractmethod
    def __init__(self, arrays): ...

    @property
    @abc.abstractmethod
    def media_dependent(self) -> bool:
        """Whether any pixel can depend on the media (False: the image is `base` alone)."""

    @abc.abstractmethod
    def empty_terms(self) -> Terms:
        """Terms of no rows (a trace in which no pixel depends on the media)."""

    def block_pixels(self, tile: int) -> int:
        """Pixels traced together (default: one `tile x tile` tile, `[render] tile`)."""
        return tile * tile

    def image_state(self, arrays, key: PRNGKeyArray) -> Any:
        """State shared by every block of one image (default: none)."""
        return None

    @abc.abstractmethod
    def trace_block(
        self, arrays, state, pixels: Int[Array, " P"], key: PRNGKeyArray, rec: Recorder = NO_RECORD
    ) -> Block:
        """Trace the flat pixel indices `pixels` (a fixed block size)."""

    def trace_rows(
        self, arrays, state, rows, valid: Bool[Array, " P"], key, rec: Recorder = NO_RECORD
    ) -> Terms:
        """Two-phase transports: the terms of packed rows (`rows` as `trace_block` returned
        them, gathered; `valid` False on padding)."""
        raise NotImplementedError(f"the {self.name} transport traces in one phase")
