"""The ray-tree recorder interface: hooks the tracing code calls where it casts rays.

Every transport function takes a recorder argument, `NO_RECORD` by default, whose hooks do
nothing (and cost nothing under `jit`). `sssjax.raytree` passes one that keeps the rays of
one pixel while it re-runs that pixel's blocks eagerly: the tree is drawn from the very code
that renders, never from a copy of it.
"""

from __future__ import annotations

from typing import ClassVar

__all__ = ["Recorder", "NO_RECORD"]


class Recorder:
    """A recorder that records nothing; subclasses override the hooks they need.

    `active` says whether rays are being recorded: recording runs eagerly and every bounce
    at full width (no packing of the alive rays), so that the hooks see every ray.
    Arrays passed to the hooks are those of the whole block (lengths in mm).
    """

    active: ClassVar[bool] = False

    def chain(self, depth, o, d, x, t_light, alive, hit_light, hit, kind, first) -> None:
        """Rays of one depth of the specular chains: origins, directions, hit points, the
        distance to a light hit, which rays were alive, hit a light, hit a shape, the
        material kind hit and whether it is the sample's first translucent hit."""

    def shadow(self, o, d, t, t_max) -> None:
        """Shadow rays `o + t d` tested against `t_max` (`t`: the nearest hit)."""

    def points(self, p, w, have) -> None:
        """Dipole source points `p` and their gather weights `w (M, n, 3)`."""

    def dipole(self, xo, p, have) -> None:
        """Per-pixel Monte Carlo dipole samples: `x_o -> p (M, K, 3)`."""

    def ss_paths(self, xo, xs, have) -> None:
        """Single scattering: `x_o -> ` each scatter point `xs (M, n, 3)`."""

    def ss_exit(self, xs, xi) -> None:
        """Single scattering towards one light: scatter point -> exit point."""

    def walk(self, event: int, rays: dict) -> None:
        """One event of volumetric walks (NumPy arrays, one row per walker recorded):
        `o -> end` (a miss ends at `o`; it leaves along `d`), the event `code` that ended
        the flight (`sssjax.transport.volumetric.EVENT`), `alive`, `inside` (a flight in a
        medium), the walker's camera `sample`, and the next-event connections tried,
        `nee_m` (from a medium vertex `x` through the boundary at `b` to the light point `y`)
        and `nee_d` (shadow rays `x -> y` from a diffuse vertex), each with `tried`, `vis`."""


NO_RECORD = Recorder()
