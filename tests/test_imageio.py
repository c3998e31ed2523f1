"""Image I/O: exact float roundtrips, the sRGB curve against published values, 8/16-bit files
written independently with OpenImageIO, and refusal of bad input."""

import json
import os

import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest

from sssjax.imageio import (
    read_image,
    read_metadata,
    srgb_decode,
    srgb_encode,
    tonemap,
    write_image,
)


def _ramp(h=6, w=7, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 1.0, size=(h, w, 3)).astype(np.float32)


def _oiio_write(path, pixels, fmt):
    """Write raw pixels with OpenImageIO directly (no sssjax code involved)."""
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    spec = oiio.ImageSpec(w, h, c, fmt)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # store colour as given, even with alpha
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(np.ascontiguousarray(pixels)), out.geterror()
    assert out.close()


def _oiio_read_raw(path):
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    spec = inp.spec()
    data = inp.read_image(spec.format)
    inp.close()
    return data, spec


# -- sRGB curve -------------------------------------------------------------------------
def test_srgb_known_values():
    # IEC 61966-2-1: straight segment 12.92 x up to 0.0031308, then 1.055 x^(1/2.4) - 0.055.
    assert srgb_encode(np.float64(0.0)) == 0.0
    assert srgb_encode(np.float64(1.0)) == pytest.approx(1.0, abs=1e-12)
    assert srgb_decode(np.float64(1.0)) == pytest.approx(1.0, abs=1e-12)
    assert srgb_encode(np.float64(0.0031308)) == pytest.approx(0.0031308 * 12.92, rel=1e-12)
    assert srgb_encode(np.float64(0.001)) == pytest.approx(0.01292, rel=1e-12)
    assert srgb_decode(np.float64(0.04045)) == pytest.approx(0.04045 / 12.92, rel=1e-12)
    assert srgb_decode(np.float64(0.02)) == pytest.approx(0.02 / 12.92, rel=1e-12)
    # Above the thresholds: the power segment (values computed by hand from the formula).
    assert srgb_encode(np.float64(0.5)) == pytest.approx(0.7353569830524495, rel=1e-12)
    assert srgb_decode(np.float64(0.5)) == pytest.approx(0.21404114048223255, rel=1e-12)
    assert srgb_encode(np.float64(0.18)) == pytest.approx(0.4613561295004, rel=1e-10)
    # The two segments meet (to the 1e-8 gap inherent in the published constants).
    eps = 1e-9
    below, above = srgb_encode(np.array([0.0031308 - eps, 0.0031308 + eps]))
    assert abs(above - below) < 1e-6


def test_srgb_roundtrip_and_dtypes():
    x = np.concatenate([np.linspace(0.0, 1.0, 10001), [0.0031308, 0.00313081, 2.0, 10.0]])
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, rtol=1e-12, atol=1e-15)
    s = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(srgb_encode(srgb_decode(s)), s, rtol=1e-12, atol=1e-15)
    # Monotone over the whole range, including across the segment joint.
    assert np.all(np.diff(srgb_encode(x[:10001])) > 0)
    x32 = x.astype(np.float32)
    assert srgb_encode(x32).dtype == np.float32
    np.testing.assert_allclose(srgb_decode(srgb_encode(x32)), x32, rtol=2e-6, atol=1e-9)
    np.testing.assert_allclose(srgb_encode(jnp.asarray(x32)), srgb_encode(x32))
    assert srgb_encode(np.array([0, 1])).dtype == np.float64  # integers promoted


# -- tone mapping -----------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["clip", "reinhard", "aces"])
@pytest.mark.parametrize("exposure", [-2.0, 0.0, 3.0])
def test_tonemap_monotone_in_unit_interval(mode, exposure):
    x = np.concatenate([[-1.0, 0.0], np.geomspace(1e-6, 1e6, 2000), [np.inf]])
    y = tonemap(x, mode, exposure)
    assert np.all((y >= 0.0) & (y <= 1.0))
    assert np.all(np.diff(y) >= 0.0)
    assert y[0] == 0.0 and y[1] == 0.0
    assert y[-2] == pytest.approx(1.0, abs=1e-5) and y[-1] == 1.0


def test_tonemap_values():
    np.testing.assert_allclose(tonemap([0.25, 2.0], "clip"), [0.25, 1.0])
    np.testing.assert_allclose(tonemap([1.0, 3.0], "reinhard"), [0.5, 0.75])
    np.testing.assert_allclose(tonemap(1.0, "aces"), 2.54 / 3.16)
    # Exposure in stops: +1 doubles the input.
    np.testing.assert_allclose(tonemap(0.5, "reinhard", 1.0), 0.5)
    np.testing.assert_allclose(tonemap(0.2, "clip", -1.0), 0.1)
    assert np.isnan(tonemap(np.nan, "aces"))  # not hidden as black; write_image rejects it
    with pytest.raises(ValueError, match="unknown tonemap 'filmic'"):
        tonemap(1.0, "filmic")


# -- float formats ----------------------------------------------------------------------
def test_exr_roundtrip_bit_exact_with_metadata(tmp_path):
    img = _ramp()
    img[0, 0] = [0.0, -0.0, 1e-40]  # zero, negative zero, a float32 denormal
    img[0, 1] = [-3.5, 65504.0, 1.0e30]  # negative and beyond the half-float range
    img[0, 2] = np.nextafter(np.float32(1.0), np.float32(2.0))
    meta = {
        "medium": "marble",
        "spp": 64,
        "scale": 0.125,
        "sigma_a": np.array([0.0021, 0.0041, 0.0071]),
        "config": {"eta": 1.3, "tags": ["a", "b"]},
        "ok": True,
    }
    path = tmp_path / "sub" / "dir" / "out.exr"  # parents are created
    assert write_image(path, img, metadata=meta) == path
    back = read_image(path)
    assert back.dtype == np.float32 and back.shape == img.shape
    assert back.tobytes() == img.tobytes()  # bit-exact, sign of zero included
    got = read_metadata(path)
    assert got == {
        "medium": "marble",
        "spp": 64,
        "scale": 0.125,
        "sigma_a": [0.0021, 0.0041, 0.0071],
        "config": {"eta": 1.3, "tags": ["a", "b"]},
        "ok": True,
    }
    # Stored as strings under the sssjax: prefix.
    _, spec = _oiio_read_raw(path)
    assert spec.get_string_attribute("sssjax:spp") == "64"
    assert json.loads(spec.get_string_attribute("sssjax:config")) == meta["config"]
    assert [p.name for p in tmp_path.rglob("*")] == ["sub", "dir", "out.exr"]  # no temp file


def test_exr_ignores_exposure_and_tonemap_and_accepts_jax(tmp_path):
    img = _ramp() * 5.0
    write_image(tmp_path / "a.exr", jnp.asarray(img), exposure=3.0, tonemap="aces")
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), img)


@pytest.mark.parametrize("ext", [".tif", ".tiff"])
def test_float_tiff_roundtrip_exact(tmp_path, ext):
    img = _ramp() * 7.0
    write_image(tmp_path / f"a{ext}", img)
    raw, spec = _oiio_read_raw(tmp_path / f"a{ext}")
    assert spec.format == oiio.TypeDesc("float")
    np.testing.assert_array_equal(read_image(tmp_path / f"a{ext}"), img)


def test_hdr_roundtrip_within_rgbe_precision(tmp_path):
    img = _ramp() * 100.0 + 0.01
    write_image(tmp_path / "a.hdr", img)
    back = read_image(tmp_path / "a.hdr")
    # RGBE: 8-bit mantissas sharing one exponent, so the error scales with the pixel's maximum.
    err = np.abs(back - img) / img.max(axis=-1, keepdims=True)
    assert err.max() <= 2.0 / 256
    assert back.dtype == np.float32 and back.max() > 50.0  # not tone mapped or clipped


# -- 8-bit display formats --------------------------------------------------------------
def test_png_encodes_srgb_8bit(tmp_path):
    levels = np.array([0.0, 0.0031308, 0.01, 0.18, 0.25, 0.5, 1.0, 4.0], np.float32)
    img = np.repeat(levels[None, :, None], 3, axis=2)
    write_image(tmp_path / "a.png", img)
    raw, spec = _oiio_read_raw(tmp_path / "a.png")
    assert spec.format == oiio.TypeDesc("uint8") and spec.nchannels == 3
    # Analytic sRGB codes, round(255 * encode(x)): linear 0.5 -> 188, 0.18 -> 118, 0.25 -> 137,
    # >= 1 -> 255.
    expected = [0, 10, 25, 118, 137, 188, 255, 255]
    np.testing.assert_array_equal(raw[0, :, 0], expected)
    np.testing.assert_array_equal(raw[0, :, 0], raw[0, :, 2])
    # Reading decodes back to linear: exactly the analytic decode of the stored code...
    back = read_image(tmp_path / "a.png")
    assert back.dtype == np.float32
    np.testing.assert_allclose(back[0, :, 0], srgb_decode(np.array(expected) / 255.0), rtol=1e-6)
    assert back[0, 5, 0] == pytest.approx(((188 / 255 + 0.055) / 1.055) ** 2.4, rel=1e-6)
    # ...which is within half an 8-bit step (in the encoded domain) of the input.
    err = np.abs(srgb_encode(back[0, :6, 0].astype(np.float64)) - srgb_encode(levels[:6]))
    assert np.all(err <= 0.5 / 255 + 1e-7)


def test_png_roundtrip_random_within_quantisation(tmp_path):
    img = _ramp(16, 16, seed=3)
    write_image(tmp_path / "r.png", img)
    back = read_image(tmp_path / "r.png").astype(np.float64)
    err = np.abs(srgb_encode(back) - srgb_encode(img.astype(np.float64)))
    assert err.max() <= 0.5 / 255 + 1e-7
    assert err.max() > 0.0  # it really was quantised (not silently stored as float)


def test_png_exposure_tonemap_and_metadata(tmp_path):
    img = np.full((2, 3, 3), 0.25, np.float32)
    write_image(tmp_path / "e.png", img, exposure=1.0, tonemap="reinhard", metadata={"spp": 8})
    raw, _ = _oiio_read_raw(tmp_path / "e.png")
    # 0.25 * 2 = 0.5 -> reinhard 1/3 -> sRGB.
    assert raw[0, 0, 0] == round(255 * float(srgb_encode(np.float64(1.0 / 3.0))))
    assert read_metadata(tmp_path / "e.png") == {"spp": 8}
    write_image(tmp_path / "c.png", img, exposure=2.0)  # clip: 1.0 -> 255
    assert _oiio_read_raw(tmp_path / "c.png")[0][0, 0, 0] == 255


def test_jpeg_roundtrip_approximate(tmp_path):
    img = np.full((8, 8, 3), 0.5, np.float32)
    for ext in (".jpg", ".jpeg", ".JPG"):
        write_image(tmp_path / f"a{ext}", img)
        raw, spec = _oiio_read_raw(tmp_path / f"a{ext}")
        assert spec.format == oiio.TypeDesc("uint8")
        assert np.all(np.abs(raw.astype(int) - 188) <= 1)
        np.testing.assert_allclose(read_image(tmp_path / f"a{ext}"), 0.5, rtol=0.01)


def test_read_16bit_png(tmp_path):
    codes = np.array([0, 1, 32768, 65535], np.uint16)
    rgb = np.stack([codes, codes[::-1], codes], axis=-1)[None]  # (1, 4, 3)
    _oiio_write(tmp_path / "d.png", rgb, "uint16")
    assert _oiio_read_raw(tmp_path / "d.png")[1].format == oiio.TypeDesc("uint16")
    back = read_image(tmp_path / "d.png")
    assert back.shape == (1, 4, 3) and back.dtype == np.float32
    np.testing.assert_allclose(back, srgb_decode(rgb / 65535.0), rtol=1e-6, atol=1e-12)
    assert back[0, 1, 0] == pytest.approx(1.0 / 65535 / 12.92, rel=1e-6)  # not 8-bit coarse
    assert back[0, 3, 0] == 1.0 and back[0, 0, 0] == 0.0


def test_read_grayscale_and_alpha(tmp_path):
    gray = np.array([[[0], [128], [255]]], np.uint8)
    _oiio_write(tmp_path / "g.png", gray, "uint8")
    back = read_image(tmp_path / "g.png")
    assert back.shape == (1, 3, 3)
    np.testing.assert_allclose(back, np.repeat(srgb_decode(gray / 255.0), 3, axis=2), rtol=1e-6)

    ga = np.array([[[128, 0], [255, 64]]], np.uint8)  # gray + alpha
    _oiio_write(tmp_path / "ga.png", ga, "uint8")
    np.testing.assert_allclose(
        read_image(tmp_path / "ga.png"),
        np.repeat(srgb_decode(ga[..., :1] / 255.0), 3, axis=2),
        rtol=1e-6,
    )

    # RGBA: alpha dropped, colour as stored (not premultiplied by alpha).
    rgba = np.array([[[188, 128, 0, 64], [255, 10, 25, 255]]], np.uint8)
    _oiio_write(tmp_path / "rgba.png", rgba, "uint8")
    back = read_image(tmp_path / "rgba.png")
    assert back.shape == (1, 2, 3)
    np.testing.assert_allclose(back, srgb_decode(rgba[..., :3] / 255.0), rtol=1e-6)

    # Float RGBA EXR: returned as stored, alpha dropped.
    f = np.array([[[0.5, 2.0, -1.0, 0.25]]], np.float32)
    _oiio_write(tmp_path / "rgba.exr", f, "float")
    np.testing.assert_array_equal(read_image(tmp_path / "rgba.exr"), f[..., :3])


def test_read_float_tagged_srgb_is_decoded(tmp_path):
    # A float file tagged sRGB is decoded too; an untagged float file is not.
    data = np.full((1, 1, 3), 0.5, np.float32)
    _oiio_write(tmp_path / "plain.tif", data, "float")
    np.testing.assert_array_equal(read_image(tmp_path / "plain.tif"), data)
    out = oiio.ImageOutput.create(str(tmp_path / "s.exr"))
    spec = oiio.ImageSpec(1, 1, 3, "float")
    spec.attribute("oiio:ColorSpace", "sRGB")
    assert out.open(str(tmp_path / "s.exr"), spec) and out.write_image(data) and out.close()
    np.testing.assert_allclose(read_image(tmp_path / "s.exr"), 0.21404114, rtol=1e-6)


# -- errors -----------------------------------------------------------------------------
def test_missing_file(tmp_path):
    missing = tmp_path / "nope.exr"
    with pytest.raises(FileNotFoundError, match=f"image not found: {missing}"):
        read_image(missing)
    with pytest.raises(FileNotFoundError, match="image not found"):
        read_metadata(missing)


def test_unreadable_file_raises_oserror(tmp_path):
    bad = tmp_path / "bad.png"
    bad.write_text("not an image")
    with pytest.raises(OSError, match="bad.png") as info:
        read_image(bad)
    assert not isinstance(info.value, FileNotFoundError)


def test_wrong_channel_count(tmp_path):
    _oiio_write(tmp_path / "five.exr", np.zeros((2, 2, 5), np.float32), "float")
    with pytest.raises(ValueError, match=r"five\.exr.*channel count 5"):
        read_image(tmp_path / "five.exr")


@pytest.mark.parametrize("shape", [(4, 4), (4, 4, 4), (4, 4, 1), (2, 4, 4, 3), (0, 4, 3)])
def test_wrong_shape(tmp_path, shape):
    path = tmp_path / "x.exr"
    with pytest.raises(ValueError, match=rf"x\.exr.*\(H, W, 3\).*{shape[0]}"):
        write_image(path, np.zeros(shape, np.float32))
    assert not path.exists()


@pytest.mark.parametrize("ext", [".exr", ".png"])
def test_nan_and_inf_pixels_refused(tmp_path, ext):
    img = _ramp()
    img[1, 2, 0] = np.nan
    img[3, 3, :] = np.nan  # same pixel counted once
    img[5, 6, 2] = np.inf
    path = tmp_path / f"n{ext}"
    with pytest.raises(ValueError, match=rf"n\{ext}.* 3 of 42 pixels") as info:
        write_image(path, img)
    assert "\n" not in str(info.value)
    assert not path.exists()


@pytest.mark.parametrize("name", ["x.bmp", "x.foo", "noext", "x.exr.txt"])
def test_unknown_extension(tmp_path, name):
    with pytest.raises(ValueError, match="unknown image extension") as info:
        write_image(tmp_path / name, _ramp())
    assert name in str(info.value)
    assert not (tmp_path / name).exists()


def test_overwrite_protection(tmp_path, monkeypatch):
    src = tmp_path / "input.png"
    write_image(src, _ramp())
    before = src.read_bytes()
    monkeypatch.chdir(tmp_path)
    # Same file by a different spelling, and through a symlink.
    os.symlink(src, tmp_path / "link.png")
    (tmp_path / "sub").mkdir()
    for target in (src, "input.png", tmp_path / "sub" / ".." / "input.png", "link.png"):
        with pytest.raises(ValueError, match="refusing to overwrite"):
            write_image(target, np.zeros((6, 7, 3)), overwrite_protect=[str(src)])
    assert src.read_bytes() == before
    # A protected path that does not exist yet is still refused.
    with pytest.raises(ValueError, match="new.exr"):
        write_image("new.exr", _ramp(), overwrite_protect=[tmp_path / "new.exr"])
    # Other paths are fine.
    write_image(tmp_path / "out.png", _ramp(), overwrite_protect=[src])
    assert (tmp_path / "out.png").exists()


def test_bad_tonemap_or_exposure(tmp_path):
    with pytest.raises(ValueError, match="unknown tonemap"):
        write_image(tmp_path / "a.png", _ramp(), tonemap="hable")
    with pytest.raises(ValueError, match="exposure"):
        write_image(tmp_path / "a.png", _ramp(), exposure=float("nan"))
    assert not (tmp_path / "a.png").exists()


def test_oiio_write_failure_is_oserror(tmp_path):
    target = tmp_path / "dir.exr"
    target.mkdir()  # a directory where the file should go
    with pytest.raises(OSError):
        write_image(target, _ramp())
    assert [p.name for p in tmp_path.iterdir()] == ["dir.exr"]  # temp file cleaned up
