"""How much memory and disk a render needs, estimated before it starts.

`estimate_memory(scene)` adds up what a render holds at its peak, from the scene's settings
alone (nothing is allocated): the image, the one array that grows with the pixel count (12
bytes a pixel: camera rays are made per tile inside the transports, and the writers work a
strip of rows at a time), and the tiles in flight, the writers' strip and the irradiance
clouds, which do not grow with it. `check_memory` turns an estimate beyond the memory
available into one line, before anything is allocated; `check_disk` does the same for the
output files. The figures are measured on the 2-core CPU
(see the constants); they are estimates to refuse the impossible, not a budget to the byte.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "TooLargeError",
    "MemoryEstimate",
    "estimate_memory",
    "available_memory",
    "check_memory",
    "output_bytes",
    "check_disk",
    "format_bytes",
]

# Measured (sssjax render of marble_cube.toml on the 2-core CPU; tracemalloc of write_image):
RUNTIME_BYTES = 1.2e9  # JAX, XLA and the compiled programs (peak RSS of a 64x64 render)
BYTES_PER_SAMPLE = 2000  # per camera sample in flight (64x64 at 256 spp: +470 MB over 16 spp)
BYTES_PER_PIXEL_IMAGE = 12  # the (H, W, 3) float32 image (24 under x64)
# write_image converts and writes a strip of rows at a time: its working copies are those of
# one strip of STRIP_PIXELS pixels, whatever the image size
STRIP_PIXELS = 1 << 16
BYTES_PER_PIXEL_PNG = 128  # per strip pixel: the float64 tone-mapping copies of an 8-bit file
BYTES_PER_PIXEL_EXR = 16  # per strip pixel: the float32 copy of a float file (4 for float32)
BYTES_PER_CLOUD_POINT = 52  # one irradiance-cloud point (position, normal, irradiance, ...)
BYTES_PER_GATHER_PAIR = 16  # one (pixel, cloud point) distance of a block's gather
# a full `Transport` (trace, fit) keeps per translucent pixel its distance histogram
# (3 channels x bins per material, float32) and the single-scattering fields
BYTES_PER_SS_SAMPLE = 40
INT32_MAX = 2**31 - 1


class TooLargeError(ValueError):
    """A render that cannot fit in memory or on disk, or past the renderer's index range."""


def format_bytes(n: float) -> str:
    """`n` bytes as `"1.5 GiB"`."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" or abs(n) >= 100 else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} PiB"  # pragma: no cover


@dataclass(frozen=True)
class MemoryEstimate:
    """Peak bytes of a render (or trace), by part. `total` is their sum."""

    runtime: float  # JAX, XLA, compiled programs
    image: float  # the image (grows with width x height) and the writers' strip (does not)
    tiles: float  # camera samples in flight (one tile per device) and a block's gather
    cloud: float  # the irradiance clouds of the translucent objects
    transport: float  # a stored `Transport` (trace, fit; 0 for a render)

    @property
    def total(self) -> float:
        return self.runtime + self.image + self.tiles + self.cloud + self.transport

    def describe(self) -> str:
        parts = [("image", self.image), ("tiles", self.tiles), ("clouds", self.cloud)]
        parts += [("transport", self.transport)]
        return ", ".join(f"{n} {format_bytes(b)}" for n, b in parts if b >= 1e6)


def estimate_memory(
    scene, *, transport: bool = False, png: bool = True, devices: int | None = None
) -> MemoryEstimate:
    """Estimate the peak memory of rendering `scene` (nothing is allocated).

    **Arguments:**

    - `scene`: a `Scene` (its camera size, `[render]` and `[sss]` settings count).
    - `transport`: estimate a `trace` / `fit` instead, which keeps a `Transport` of every
      translucent pixel (taken as every pixel: an upper bound).
    - `png`: the image is also written to an 8-bit file (the largest writer copies).
    - `devices`: JAX devices the tiles run on (default: `jax.device_count()`).

    **Returns:** a `MemoryEstimate` in bytes.
    """
    if devices is None:
        import jax

        devices = jax.device_count()
    cam, rs, sss = scene.camera, scene.render, scene.sss
    n_pix = cam.width * cam.height
    block = min(rs.tile**2, n_pix)
    writer = min(n_pix, STRIP_PIXELS) * (BYTES_PER_PIXEL_PNG if png else BYTES_PER_PIXEL_EXR)
    image = n_pix * BYTES_PER_PIXEL_IMAGE + writer
    n_tobj = sum(1 for s in scene.shapes if scene.materials[s.material].type == "translucent")
    sss_on = sss.enabled and n_tobj > 0
    tiles = devices * block * rs.spp * BYTES_PER_SAMPLE
    cloud = 0.0
    if sss_on:
        cloud = n_tobj * sss.cloud_size * BYTES_PER_CLOUD_POINT
        tiles += devices * block * sss.cloud_size * BYTES_PER_GATHER_PAIR
    stored = 0.0
    if transport:
        n_mat = max(1, len(scene.translucent_materials))
        per_px = 4 * 3 * sss.bins * n_mat + BYTES_PER_SS_SAMPLE * rs.spp * sss.single_samples
        stored = n_pix * (per_px if sss_on else 0) + n_pix * 16  # + base radiance, indices
    return MemoryEstimate(RUNTIME_BYTES, image, tiles, cloud, stored)


def available_memory() -> float | None:
    """Bytes of memory this process may still use: the smaller of the system's available
    memory (`MemAvailable`) and the cgroup's limit, or `None` where unknown."""
    found = []
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found.append(float(line.split()[1]) * 1024)
    except OSError:
        pass
    if not found:
        try:
            found.append(float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")))
        except (ValueError, OSError, AttributeError):
            pass
    for limit in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(limit).read_text().strip()
            if text.isdigit() and int(text) < 2**60:
                found.append(float(text))
        except OSError:
            pass
    return min(found) if found else None


def check_memory(
    scene, *, transport: bool = False, png: bool = True, available: float | None = None
) -> MemoryEstimate:
    """Refuse, in one line, a render that cannot fit in memory or that the renderer cannot
    index (more than 2^31 - 1 pixels, or camera samples in one tile).

    **Arguments:** `scene`, `transport`, `png` as `estimate_memory`; `available` bytes
    (default: `available_memory()`).

    **Returns:** the `MemoryEstimate`.

    **Raises:** `TooLargeError`.
    """
    cam, rs = scene.camera, scene.render
    size = f"a {cam.width}x{cam.height} {'trace' if transport else 'render'} at {rs.spp} spp"
    est = estimate_memory(scene, transport=transport, png=png)
    avail = available_memory() if available is None else available
    # the runtime is loaded already (and not in the available memory): the rest is to come
    need = est.total - est.runtime
    if avail is not None and need > avail:
        biggest = max(("image", "tiles", "cloud", "transport"), key=lambda p: getattr(est, p))
        advice = {
            "image": "lower --width / --height",
            "tiles": "lower --spp (or [render] tile, [sss] cloud_size)",
            "cloud": "lower [sss] cloud_size",
            "transport": "lower --width / --height",
        }[biggest]
        raise TooLargeError(
            f"{size} needs about {format_bytes(need)} more memory ({est.describe()}), "
            f"more than the {format_bytes(avail)} available: {advice}"
        )
    n_pix = cam.width * cam.height
    if n_pix > INT32_MAX:
        raise TooLargeError(
            f"{size} has {n_pix:.3g} pixels, more than the 2^31 - 1 the renderer indexes: "
            "lower --width / --height"
        )
    block = min(rs.tile**2, n_pix)
    if block * rs.spp > INT32_MAX:
        raise TooLargeError(
            f"{size} traces {block * rs.spp:.3g} camera samples per tile, more than 2^31 - 1: "
            "lower --spp or [render] tile"
        )
    return est


def output_bytes(path: str | os.PathLike, width: int, height: int) -> int:
    """Upper bound on the size of an image file of `width x height` RGB pixels (uncompressed
    float32 for EXR / TIFF / HDR, 8-bit for PNG / JPEG, plus a header)."""
    ext = Path(path).suffix.lower()
    per = 3 if ext in (".png", ".jpg", ".jpeg") else 12
    return width * height * per + 65536


def check_disk(paths, width: int, height: int) -> None:
    """Refuse, in one line, outputs that cannot fit on their disks (all of them at once).

    **Raises:** `TooLargeError`."""
    need: dict[str, list] = {}
    for p in paths:
        folder = Path(p).resolve().parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        try:
            dev = os.stat(folder).st_dev
            free = shutil.disk_usage(folder).free
        except OSError:
            continue
        entry = need.setdefault(str(dev), [0, free, folder])
        entry[0] += output_bytes(p, width, height)
    for total, free, folder in need.values():
        if total > free:
            raise TooLargeError(
                f"the {width}x{height} outputs need up to {format_bytes(total)} on disk, more "
                f"than the {format_bytes(free)} free in {folder}"
            )
