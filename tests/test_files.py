"""Never lose a file: the one overwrite rule of every command, and atomic writes (an
interrupted write leaves the old file intact and no temporary file)."""

import json

import matplotlib
import numpy as np
import pytest

from sssjax import _files
from sssjax.cli import main
from sssjax.imageio import read_image, write_image

matplotlib.use("Agg")

SMALL = """
[camera]
origin = [0.0, 20.0, 40.0]
target = [0.0, 0.0, 0.0]
width = 8
height = 8

[render]
spp = 1
light_samples = 1

[[lights]]
type = "point"
position = [0.0, 30.0, 10.0]
intensity = 500.0

[materials.white]
type = "diffuse"
albedo = 0.5

[[shapes]]
type = "sphere"
material = "white"
radius = 5.0
"""


def leftovers(folder):
    """Temporary files of `_files.atomic` anywhere below `folder`."""
    return [p for p in folder.rglob("*") if _files.is_temporary(p)]


def test_check_outputs_rule(tmp_path):
    a, b = tmp_path / "a.png", tmp_path / "b.exr"
    assert _files.check_outputs([a, b], force=False) == [a, b]  # nothing exists: fine
    a.write_bytes(b"old")
    with pytest.raises(FileExistsError, match=r"a\.png exists; use --force"):
        _files.check_outputs([a, b], force=False)
    b.write_bytes(b"old")
    with pytest.raises(
        FileExistsError, match=r"a\.png exists; use --force to overwrite it and .*b\.exr \(or"
    ):
        _files.check_outputs([a, b], force=False)
    _files.check_outputs([a, b], force=True)
    scene = tmp_path / "s.toml"
    scene.write_text("x")
    for force in (False, True):  # an input is never an output
        with pytest.raises(ValueError, match="refusing to overwrite the input file"):
            _files.check_outputs([tmp_path / "sub" / ".." / "s.toml"], force=force, inputs=[scene])
    with pytest.raises(ValueError, match="named twice"):
        _files.check_outputs([b, tmp_path / "b.exr"], force=True)
    assert a.read_bytes() == b"old" and b.read_bytes() == b"old"


def test_atomic_write_replaces_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "deep" / "r.json"
    _files.write_text(p, '{"a": 1}')
    assert json.loads(p.read_text()) == {"a": 1}
    _files.write_text(p, '{"a": 2}')
    assert json.loads(p.read_text()) == {"a": 2}
    assert leftovers(tmp_path) == []
    with pytest.raises(FileExistsError):
        _files.write_text(p, "new", overwrite=False)
    assert json.loads(p.read_text()) == {"a": 2} and leftovers(tmp_path) == []


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()])
def test_interrupted_write_keeps_the_old_file(tmp_path, error):
    p = tmp_path / "r.json"
    p.write_text("precious")
    with pytest.raises(type(error)):
        with _files.atomic(p) as tmp:
            tmp.write_text("half a fi")  # the write has started ...
            raise error  # ... and dies (Ctrl-C, a full disk)
    assert p.read_text() == "precious"
    assert leftovers(tmp_path) == []


def test_interrupted_image_write_keeps_the_old_image(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    p = tmp_path / "img.exr"
    old = np.full((4, 5, 3), 0.25, np.float32)
    write_image(p, old)
    before = p.read_bytes()
    real_create = oiio.ImageOutput.create

    class Dying:  # OpenImageIO's writer, killed after the header and a first strip of rows
        def __init__(self, path):
            self.out = real_create(path)

        def open(self, path, spec):
            return self.out.open(path, spec)

        def write_scanlines(self, y0, y1, z, pixels):
            self.out.write_scanlines(y0, y1, z, pixels)
            raise KeyboardInterrupt

        def close(self):
            return self.out.close()

    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda path: Dying(path)))
    with pytest.raises(KeyboardInterrupt):
        write_image(p, np.ones((4, 5, 3)))
    monkeypatch.undo()
    assert p.read_bytes() == before
    np.testing.assert_array_equal(read_image(p), old)
    assert leftovers(tmp_path) == []
    write_image(p, np.ones((4, 5, 3)))  # and a write that completes replaces it
    np.testing.assert_array_equal(read_image(p), np.ones((4, 5, 3)))
    assert leftovers(tmp_path) == []


def test_interrupted_plot_keeps_the_old_png(tmp_path, monkeypatch):
    import matplotlib.figure

    from sssjax.plots import plot_profiles

    p = tmp_path / "rd.png"
    plot_profiles(["marble"], p)
    before = p.read_bytes()
    assert before[:8] == b"\x89PNG\r\n\x1a\n"
    real = matplotlib.figure.Figure.savefig

    def dying(self, fname, **kw):
        real(self, fname, **kw)
        with open(fname, "r+b") as f:
            f.truncate(100)  # half written ...
        raise OSError("disk full")  # ... and the disk is full

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", dying)
    with pytest.raises(OSError, match="disk full"):
        plot_profiles(["skin1"], p)
    assert p.read_bytes() == before and leftovers(tmp_path) == []


def test_free_stem_is_the_previewers_rule(tmp_path):
    base = tmp_path / "view"
    first = _files.free_stem(base, (".png", ".exr", ".toml"))
    assert {p.name for p in first.values()} == {"view.png", "view.exr", "view.toml"}
    (tmp_path / "view.exr").write_bytes(b"x")  # any one file takes the stem
    assert _files.free_stem(base, (".png", ".exr"))["png"].name == "view_1.png"
    assert _files.free_stem(tmp_path / "s", (".toml",), protect=[tmp_path / "s.toml"])[
        "toml"
    ].name == ("s_1.toml")


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    (d / "s.toml").write_text(SMALL)
    return d / "s.toml"


def test_render_refuses_an_existing_output_unless_force(small_scene, tmp_path, capsys):
    png, exr = tmp_path / "photo.png", tmp_path / "photo.exr"
    png.write_bytes(b"my holiday photo")
    args = ["render", str(small_scene), "-o", str(exr), "-o", str(png)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "photo.png exists; use --force" in err and len(err.strip().splitlines()) == 1
    assert png.read_bytes() == b"my holiday photo"
    assert not exr.exists()  # refused before anything was rendered or written
    assert main([*args, "--force"]) == 0
    assert read_image(png).shape == (8, 8, 3) and read_image(exr).shape == (8, 8, 3)
    assert leftovers(tmp_path) == []


def test_demo_refuses_an_existing_output_unless_force(tmp_path, capsys):
    (tmp_path / "marble_cube.exr").write_bytes(b"mine")
    assert main(["demo", "--out", str(tmp_path), "--size", "8", "--spp", "1"]) == 2
    assert "marble_cube.exr exists; use --force" in capsys.readouterr().err
    assert (tmp_path / "marble_cube.exr").read_bytes() == b"mine"
    assert not (tmp_path / "rd_profiles.png").exists()


def test_measure_refuses_an_existing_output_unless_force(tmp_path, capsys):
    img = tmp_path / "beam.exr"
    write_image(img, np.ones((8, 8, 3)))
    out = tmp_path / "m"
    out.mkdir()
    (out / "profile.png").write_bytes(b"mine")
    assert main(["measure", str(img), "--pixel-size", "0.1", "-o", str(out)]) == 2
    assert "profile.png exists; use --force" in capsys.readouterr().err
    assert (out / "profile.png").read_bytes() == b"mine"
