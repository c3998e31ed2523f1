"""Reading and writing images through OpenImageIO.

In memory an image is always an `(H, W, 3)` array of **linear** RGB. On disk:

- `.exr`, `.hdr`, `.tif`/`.tiff` hold linear float32 (bit-exact for `.exr` and `.tif`; `.hdr`
  is Radiance RGBE, precise to about 1/256 of each pixel's brightest channel). `metadata` is
  stored as string attributes named `sssjax:<key>` (kept by EXR; TIFF and HDR drop them).
- `.png`, `.jpg`/`.jpeg` hold 8-bit sRGB for display: the image is multiplied by
  `2**exposure`, tone mapped into `[0, 1]`, sRGB-encoded and rounded. PNG keeps `metadata`
  as text chunks.

Reading decodes 8/16-bit and sRGB-tagged files back to linear with the exact sRGB curve.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
from jaxtyping import ArrayLike

from ._budget import STRIP_PIXELS  # pixels per strip of rows that `write_image` writes
from ._files import atomic

__all__ = [
    "FLOAT_EXTENSIONS",
    "DISPLAY_EXTENSIONS",
    "TONEMAPS",
    "METADATA_PREFIX",
    "write_image",
    "read_image",
    "read_metadata",
    "render_metadata",
    "srgb_encode",
    "srgb_decode",
    "tonemap",
]

FLOAT_EXTENSIONS = (".exr", ".hdr", ".tif", ".tiff")
DISPLAY_EXTENSIONS = (".png", ".jpg", ".jpeg")
TONEMAPS = ("clip", "reinhard", "aces")
METADATA_PREFIX = "sssjax:"

# IEC 61966-2-1 sRGB transfer function.
_SRGB_LINEAR_MAX = 0.0031308  # linear values up to here are on the straight segment
_SRGB_ENCODED_MAX = 0.04045  # encoded values up to here are on the straight segment
_SRGB_SLOPE = 12.92
_SRGB_A = 0.055
_SRGB_GAMMA = 2.4

_LINEAR_COLORSPACE = "lin_rec709_scene"
_SRGB_COLORSPACE = "sRGB"


# -- transfer curves and tone mapping ---------------------------------------------------
def _float_array(x: ArrayLike) -> np.ndarray:
    a = np.asarray(x)
    return a if np.issubdtype(a.dtype, np.floating) else a.astype(np.float64)


def srgb_encode(linear: ArrayLike) -> np.ndarray:
    """Linear -> sRGB-encoded values with the exact IEC 61966-2-1 piecewise curve.

    **Arguments:** `linear`, any shape (numpy or jax). Values `<= 0.0031308` (negatives
    included) are on the straight segment `12.92 x`; values above `1` continue the power law.

    **Returns:** a numpy array of the same shape (float64 unless the input is a float type).
    """
    x = _float_array(linear)
    x64 = x.astype(np.float64)
    power = (1.0 + _SRGB_A) * np.power(
        np.maximum(x64, _SRGB_LINEAR_MAX), 1.0 / _SRGB_GAMMA
    ) - _SRGB_A
    out = np.where(x64 <= _SRGB_LINEAR_MAX, _SRGB_SLOPE * x64, power)
    return out.astype(x.dtype, copy=False)


def srgb_decode(srgb: ArrayLike) -> np.ndarray:
    """sRGB-encoded -> linear values with the exact IEC 61966-2-1 piecewise curve.

    **Arguments:** `srgb`, any shape (numpy or jax), nominally in `[0, 1]`. Values `<= 0.04045`
    (negatives included) are on the straight segment `s / 12.92`.

    **Returns:** a numpy array of the same shape (float64 unless the input is a float type).
    """
    s = _float_array(srgb)
    s64 = s.astype(np.float64)
    power = np.power((np.maximum(s64, _SRGB_ENCODED_MAX) + _SRGB_A) / (1.0 + _SRGB_A), _SRGB_GAMMA)
    out = np.where(s64 <= _SRGB_ENCODED_MAX, s64 / _SRGB_SLOPE, power)
    return out.astype(s.dtype, copy=False)


def tonemap(image: ArrayLike, mode: str = "clip", exposure: float = 0.0) -> np.ndarray:
    """Map linear radiance to display-linear values in `[0, 1]` (before sRGB encoding).

    **Arguments:**

    - `image`: linear values, any shape (numpy or jax).
    - `mode`: `"clip"` (clamp to `[0, 1]`), `"reinhard"` (`x / (1 + x)`) or `"aces"`
      (Narkowicz's 2015 fit `x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)`, clamped; no
      implicit pre-exposure).
    - `exposure`: in stops; the image is multiplied by `2**exposure` first.

    Negative values map to 0. NaN is passed through (callers reject it beforehand).

    **Returns:** a float64 numpy array of the same shape, non-decreasing in the input.
    """
    if mode not in TONEMAPS:
        raise ValueError(f"unknown tonemap {mode!r}; expected one of {', '.join(TONEMAPS)}")
    exposure = float(exposure)
    if not np.isfinite(exposure):
        raise ValueError(f"exposure must be finite, got {exposure:g}")
    x = np.asarray(image, dtype=np.float64) * 2.0**exposure
    x = np.where(x < 0.0, 0.0, x) + 0.0  # negatives (and -0.0) to 0.0; NaN stays NaN
    if mode == "reinhard":
        x = np.minimum(x, 1e300)  # so that inf gives 1 instead of inf / inf
        x = x / (1.0 + x)
    elif mode == "aces":
        x = np.minimum(x, 1e6)  # the fit has saturated long before; avoids inf / inf
        x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    return np.clip(x, 0.0, 1.0)


# -- helpers ----------------------------------------------------------------------------
def _extension(path: Path) -> str:
    return path.suffix.lower()


def _check_extension(path: Path) -> str:
    ext = _extension(path)
    if ext not in FLOAT_EXTENSIONS + DISPLAY_EXTENSIONS:
        known = ", ".join(FLOAT_EXTENSIONS + DISPLAY_EXTENSIONS)
        raise ValueError(f"{path}: unknown image extension {ext or '(none)'!r}; expected {known}")
    return ext


def _same_file(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "__array__"):
        arr = np.asarray(obj)
        return arr.item() if arr.ndim == 0 else arr.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"metadata value of type {type(obj).__name__} is not JSON serialisable")


def _metadata_attributes(metadata: Mapping[str, Any] | None) -> dict[str, str]:
    attrs: dict[str, str] = {}
    for key, value in (metadata or {}).items():
        name = str(key)
        if not name.startswith(METADATA_PREFIX):
            name = METADATA_PREFIX + name
        attrs[name] = value if isinstance(value, str) else json.dumps(value, default=_json_default)
    return attrs


def _oiio_error(obj: Any = None) -> str:
    msg = obj.geterror() if obj is not None else ""
    msg = msg or oiio.geterror()
    return " ".join(msg.split()) or "unknown OpenImageIO error"


# -- writing ----------------------------------------------------------------------------
_tonemap = tonemap  # `write_image` has an argument named `tonemap`


def write_image(
    path: str | os.PathLike,
    image: ArrayLike,
    *,
    metadata: Mapping[str, Any] | None = None,
    exposure: float = 0.0,
    tonemap: str = "clip",
    overwrite_protect: Iterable[str | os.PathLike] = (),
    overwrite: bool = True,
) -> Path:
    """Write a linear-RGB image; the format follows the extension of `path`.

    **Arguments:**

    - `path`: output file; `.exr`, `.hdr`, `.tif`/`.tiff` (linear float32) or `.png`,
      `.jpg`/`.jpeg` (8-bit sRGB). Missing parent folders are created.
    - `image`: `(H, W, 3)` linear RGB, numpy or jax, all values finite.
    - `metadata`: stored as string attributes `sssjax:<key>` (values that are not `str` are
      JSON-encoded) in EXR files and PNG text chunks; other formats drop it.
    - `exposure`: stops applied before tone mapping (8-bit formats only).
    - `tonemap`: `"clip"`, `"reinhard"` or `"aces"`, see `tonemap` (8-bit formats only).
    - `overwrite_protect`: paths that must not be written (e.g. the caller's input files).
    - `overwrite`: `False` fails with `FileExistsError` rather than replace an existing file.

    The file is written under a temporary name in the same folder and then renamed
    (`sssjax._files.atomic`), so a failed or interrupted write leaves the old file intact and
    no partial file behind. The image is converted and written a strip of rows
    (`STRIP_PIXELS` pixels) at a time, so the writer's working memory does not grow with it.

    **Returns:** the `Path` written.

    **Raises:** `ValueError` for an unknown extension, a protected path, a wrong shape,
    non-finite pixels or a bad `tonemap`/`exposure`; `OSError` when OpenImageIO fails.
    """
    path = Path(path)
    ext = _check_extension(path)
    for protected in overwrite_protect:
        if _same_file(path, Path(protected)):
            raise ValueError(f"{path}: refusing to overwrite an input file ({protected})")
    tonemap_mode = tonemap
    if tonemap_mode not in TONEMAPS:
        raise ValueError(
            f"{path}: unknown tonemap {tonemap_mode!r}; expected one of {', '.join(TONEMAPS)}"
        )
    if not np.isfinite(float(exposure)):
        raise ValueError(f"{path}: exposure must be finite, got {float(exposure):g}")

    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"{path}: image must have shape (H, W, 3), got {img.shape}")
    if img.dtype.kind not in "biuf":
        raise ValueError(f"{path}: image must be numeric, got dtype {img.dtype}")
    height, width = img.shape[:2]
    # the image is checked, converted and written a strip of rows at a time: the working
    # copies are those of one strip (`STRIP_PIXELS`), whatever the image size
    rows = max(1, STRIP_PIXELS // width)
    strips = [(y, min(y + rows, height)) for y in range(0, height, rows)]
    dt = np.float32 if ext in FLOAT_EXTENSIONS else np.float64  # what is finite once written

    def n_bad(y0: int, y1: int) -> int:
        return int((~np.all(np.isfinite(np.asarray(img[y0:y1], dtype=dt)), axis=-1)).sum())

    bad = sum(n_bad(y0, y1) for y0, y1 in strips)
    if bad:
        raise ValueError(
            f"{path}: refusing to write {bad} of {height * width} pixels with NaN or inf"
        )

    if ext in FLOAT_EXTENSIONS:
        spec = oiio.ImageSpec(width, height, 3, "float")
        spec.attribute("oiio:ColorSpace", _LINEAR_COLORSPACE)

        def strip(y0: int, y1: int) -> np.ndarray:
            return np.ascontiguousarray(img[y0:y1], dtype=np.float32)

    else:
        spec = oiio.ImageSpec(width, height, 3, "uint8")
        spec.attribute("oiio:ColorSpace", _SRGB_COLORSPACE)

        def strip(y0: int, y1: int) -> np.ndarray:
            display = srgb_encode(_tonemap(img[y0:y1], tonemap_mode, exposure))
            return np.ascontiguousarray(np.clip(np.rint(display * 255.0), 0, 255).astype(np.uint8))

    if ext in (".exr", ".png"):
        for name, value in _metadata_attributes(metadata).items():
            spec.attribute(name, value)
    elif metadata:
        _metadata_attributes(metadata)  # still reject values that cannot be encoded

    with atomic(path, overwrite=overwrite) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OSError(f"{path}: cannot write: {_oiio_error()}")
        ok = out.open(str(tmp), spec)
        for y0, y1 in strips:
            ok = ok and out.write_scanlines(y0, y1, 0, strip(y0, y1))
        ok = out.close() and ok
        if not ok:
            raise OSError(f"{path}: cannot write: {_oiio_error(out)}")
    return path


# -- reading ----------------------------------------------------------------------------
def _open(path: str | os.PathLike) -> tuple[Path, Any]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # keep colour as stored, not premultiplied
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise OSError(f"{path}: cannot read: {_oiio_error()}")
    return path, inp


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image as linear RGB.

    **Arguments:** `path`, any format OpenImageIO reads.

    8- and 16-bit integer files and files tagged sRGB are decoded to linear with the exact sRGB
    curve; float files (EXR, HDR, float TIFF) are returned as stored. One channel (grayscale)
    is broadcast to RGB; an alpha channel is dropped (colour is not premultiplied).

    **Returns:** a float32 numpy array of shape `(H, W, 3)`.

    **Raises:** `FileNotFoundError` for a missing file, `ValueError` for a channel count other
    than gray, gray + alpha, RGB or RGBA, `OSError` when OpenImageIO fails.
    """
    path, inp = _open(path)
    try:
        spec = inp.spec()
        fmt = spec.format
        integer = fmt.basetype in (oiio.UINT8, oiio.UINT16)
        data = inp.read_image(fmt if integer else oiio.TypeDesc("float"))
        if data is None:
            raise OSError(f"{path}: cannot read: {_oiio_error(inp)}")
        colorspace = spec.get_string_attribute("oiio:ColorSpace")
        nchannels, alpha = spec.nchannels, spec.alpha_channel
    finally:
        inp.close()

    data = np.asarray(data).reshape(spec.height, spec.width, nchannels)
    if nchannels in (2, 4) and alpha == nchannels - 1:
        data = data[..., : nchannels - 1]
    if data.shape[-1] not in (1, 3):
        raise ValueError(
            f"{path}: unsupported channel count {nchannels} (expected 1 gray, 2 gray+alpha, "
            f"3 RGB or 4 RGBA)"
        )
    if integer:
        linear = srgb_decode(data.astype(np.float64) / np.iinfo(data.dtype).max)
    elif colorspace.lower().startswith("srgb"):  # "sRGB", "srgb_rec709_scene"; not "lin_srgb"
        linear = srgb_decode(data.astype(np.float64))
    else:
        linear = data
    linear = np.asarray(linear, dtype=np.float32)
    return np.ascontiguousarray(np.broadcast_to(linear, (*linear.shape[:2], 3)))


def read_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The `sssjax:` attributes of an image file, as written by `write_image(metadata=...)`.

    **Arguments:** `path`, an image file.

    **Returns:** a dict keyed without the `sssjax:` prefix; values are JSON-decoded where
    they parse as JSON and left as strings otherwise (so a `str` value that happens to be
    valid JSON, e.g. `"16"`, comes back decoded).
    """
    path, inp = _open(path)
    try:
        params = list(inp.spec().extra_attribs)
    finally:
        inp.close()
    result: dict[str, Any] = {}
    for p in params:
        if not p.name.startswith(METADATA_PREFIX):
            continue
        value = p.value
        if isinstance(value, str):
            try:
                value = json.loads(value)
            except ValueError:
                pass
        result[p.name[len(METADATA_PREFIX) :]] = value
    return result


def render_metadata(scene, **extra: Any) -> dict[str, Any]:
    """The metadata sssjax stores with a rendered image of `scene` (a `Scene`): where it came
    from, its samples and SSS switch, the camera (and an orthographic camera's pixel size,
    mm), the translucent media (coefficients in 1/mm), the beam lights, the version and the
    units; `extra` (the `seed`, or a viewer's `seeds` and total `spp`) is added last.

    `sssjax measure` reads `pixel_size_mm`, `media` (`eta`), `beams`, `transport` and
    `profile` back from it.
    """
    from ._version import __version__

    cam = scene.camera
    meta: dict[str, Any] = {
        "scene": scene.path or "<dict>",
        "spp": scene.render.spp,
        "light_samples": scene.render.light_samples,
        "sss": scene.sss.enabled,
        "version": __version__,
        "units": "radiance; lengths mm, coefficients 1/mm",
        "camera": {
            "origin": [float(x) for x in cam.origin],
            "target": [float(x) for x in cam.target],
            "up": [float(x) for x in cam.up],
            "fov": float(cam.fov),
            "projection": cam.projection,
        },
        "media": {
            n: {
                "sigma_a": np.asarray(m.sigma_a).tolist(),
                "sigma_s": np.asarray(m.sigma_s).tolist(),
                "g": float(np.asarray(m.g).mean()),
                "eta": float(m.eta),
            }
            for n, m in scene.media().items()
        },
    }
    if cam.projection == "orthographic":
        meta["pixel_size_mm"] = cam.pixel_size_mm
    # `sssjax measure` needs it: the diffusion transport renders a beam's multiple
    # scattering only (no single scattering under the beam)
    meta["transport"] = scene.sss.transport
    meta["profile"] = scene.sss.profile
    beams = [b for b in scene.lights if b.kind == "beam"]
    if beams:
        meta["beams"] = [
            {
                "position": np.asarray(b.position).tolist(),
                "direction": np.asarray(b.direction).tolist(),
                "radius": float(b.radius),
                "power": np.asarray(b.power).tolist(),
            }
            for b in beams
        ]
    meta.update(extra)
    return meta
