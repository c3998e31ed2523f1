"""An error for every bad input: each command line of tests/data/bad_cli.toml and each fit file
of tests/data/bad_fits gives its one promised line (exit status 2, no traceback, nothing
written); a scene without lights warns in one line and renders only the background; a render
too large for the machine is refused from its memory estimate before anything is allocated."""

import tomllib
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

import sssjax
from sssjax import _budget
from sssjax.cli import main
from sssjax.scene import SceneError, SceneWarning, load_scene

DATA = Path(__file__).parent / "data"
CLI_CASES = tomllib.loads((DATA / "bad_cli.toml").read_text())["case"]
BAD_FITS = sorted((DATA / "bad_fits").glob("*.toml"))


def expected(path: Path) -> str:
    first = path.read_text().splitlines()[0]
    assert first.startswith("# expect: ")
    return first[len("# expect: ") :]


def run_cli(argv, capsys) -> tuple[int, str]:
    """`sssjax ARGV` in this process: its exit status and stderr (argparse's exits too)."""
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse: usage and one error line
        rc = e.code
    return rc, capsys.readouterr().err


def files_below(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*")}


@pytest.mark.parametrize(
    "case",
    CLI_CASES,
    ids=[f"{i:02d}-{' '.join(c['args'][:1] + c['args'][2:4])}" for i, c in enumerate(CLI_CASES)],
)
def test_bad_command_line_is_one_line(case, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # default outputs (out/...) would land here
    argv = [a.format(data=DATA, tmp=tmp_path) for a in case["args"]]
    before = files_below(DATA)
    rc, err = run_cli(argv, capsys)
    assert rc == 2, err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert case["expect"] in last, err
    if not last.startswith("usage:") and "error: argument" not in last:
        assert len(err.strip().splitlines()) == 1, err  # ours: one line (argparse adds usage)
    assert files_below(DATA) == before  # nothing written next to the inputs
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # nor anywhere else


@pytest.mark.parametrize("path", BAD_FITS, ids=[p.stem for p in BAD_FITS])
def test_bad_fit_file_is_one_line(path, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, err = run_cli(["fit", str(path), "-o", str(tmp_path / "res")], capsys)
    assert rc == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert expected(path) in err, err
    if path.stem not in ("scene_missing", "target_corrupt", "target_not_an_image"):
        assert str(path) in err  # names the fit file (or the file it points to)
    assert not (tmp_path / "res").exists()


def test_scene_folder_and_cli_no_shapes(tmp_path, capsys):
    with pytest.raises(SceneError, match="is a folder, not a scene file"):
        load_scene(tmp_path)


NO_LIGHTS = """
[camera]
origin = [0.0, 0.0, 40.0]
target = [0.0, 0.0, 0.0]
width = 16
height = 16

[render]
spp = 1
background = [0.1, 0.2, 0.3]

[materials.white]
type = "diffuse"
albedo = 0.8

[[shapes]]
type = "sphere"
material = "white"
radius = 5.0
"""


def test_no_lights_warns_once_and_renders_only_the_background(tmp_path, capsys):
    path = tmp_path / "dark.toml"
    path.write_text(NO_LIGHTS)
    with pytest.warns(SceneWarning, match=r"dark\.toml: no \[\[lights\]\]: the image shows only"):
        scene = load_scene(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a lit scene does not warn
        load_scene(DATA / "tiny_scene.toml")
    image = sssjax.render(scene, 0)
    bg = np.array([0.1, 0.2, 0.3], image.dtype)
    # every pixel is the background times the fraction of its sample that misses the sphere
    # (an unlit diffuse sphere is black): nothing is lit that no light could light
    frac = image[..., 0] / bg[0]
    np.testing.assert_allclose(image, frac[..., None] * bg, rtol=1e-5, atol=1e-7)
    assert frac.min() == 0.0 and frac.max() == 1.0
    assert image[8, 8].max() == 0.0 and np.array_equal(image[0, 0], bg.astype(image.dtype))
    # the command line says it in one line and still writes the image
    out = tmp_path / "dark.exr"
    assert main(["render", str(path), "-o", str(out)]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert err == [
        f"sssjax: warning: {path}: no [[lights]]: the image shows only the background "
        "(and what reflects it)"
    ]
    assert out.exists()


def test_dark_lights_warn_too(tmp_path):
    d = tomllib.loads((DATA / "tiny_scene.toml").read_text())
    d["lights"][0]["intensity"] = 0.0
    with pytest.warns(SceneWarning, match="every light has zero emission"):
        load_scene(d)


def test_too_large_is_refused_before_allocating(tmp_path):
    scene = load_scene(DATA / "tiny_scene.toml").with_settings(width=400_000, height=400_000)
    est = _budget.estimate_memory(scene, devices=1)
    # the image is the one array that grows with the pixels (12 bytes each); the writers' is
    # one strip of rows
    strip = _budget.STRIP_PIXELS * _budget.BYTES_PER_PIXEL_PNG
    assert est.image == 1.6e11 * _budget.BYTES_PER_PIXEL_IMAGE + strip
    tracemalloc.start()
    with pytest.raises(
        _budget.TooLargeError, match=r"400000x400000 render .* needs about 1.7\d TiB"
    ):
        sssjax.render(scene, 0)  # the library refuses it too (Renderer), in one line
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 50e6  # nothing image-sized was allocated
    small = load_scene(DATA / "tiny_scene.toml")
    assert _budget.check_memory(small).total < 2e9  # a small render passes
    with pytest.raises(_budget.TooLargeError, match=r"more than the 1 MiB available"):
        _budget.check_memory(small.with_settings(width=512, height=512), available=2**20)


def test_disk_check(tmp_path):
    _budget.check_disk([tmp_path / "a.exr"], 64, 64)
    with pytest.raises(_budget.TooLargeError, match="on disk, more than the"):
        _budget.check_disk([tmp_path / "a.exr", tmp_path / "b.png"], 2_000_000, 2_000_000)


@pytest.mark.parametrize("ext", ["png", "exr"])
def test_image_estimate_bounds_the_writers_peak(tmp_path, ext):
    """write_image works a strip of rows at a time: its peak is the per-pixel constant times
    a strip's pixels (measured; a float64 image is the worst case), for an image of one
    strip as for one of eight."""
    from sssjax.imageio import write_image

    per_px = _budget.BYTES_PER_PIXEL_PNG if ext == "png" else _budget.BYTES_PER_PIXEL_EXR
    strip = _budget.STRIP_PIXELS * per_px
    w = 512
    for strips, dtype in ((1, np.float64), (8, np.float64), (8, np.float32)):
        h = strips * _budget.STRIP_PIXELS // w
        image = np.random.default_rng(0).random((h, w, 3), dtype=dtype)
        tracemalloc.start()
        write_image(tmp_path / f"x.{ext}", image)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert peak <= 1.05 * strip + 1e5, (strips, dtype, peak)
        if dtype == np.float64:
            assert peak >= 0.7 * strip, (strips, peak)  # the constant is not a loose bound
        if strips > 1:
            assert peak < h * w * per_px / 4  # not the whole image converted at once


def test_render_takes_the_seed_by_name():
    scene = load_scene(DATA / "tiny_scene.toml")
    np.testing.assert_array_equal(sssjax.render(scene, seed=3), sssjax.render(scene, 3))
    assert not np.array_equal(sssjax.render(scene, seed=3), sssjax.render(scene, seed=4))
    with pytest.raises(TypeError, match="not both"):
        sssjax.render(scene, 3, seed=3)
