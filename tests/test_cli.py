"""The command line: tables, demo output, one-line errors."""

import numpy as np

from sssjax import dipole, preset
from sssjax.cli import main
from sssjax.imageio import read_image, read_metadata


def test_materials_prints_every_preset_with_derived_values(capsys):
    assert main(["materials"]) == 0
    out = capsys.readouterr().out
    m = preset("marble")
    total = np.asarray(dipole.Rd_total(m.sigma_a, m.sigmap_s, m.eta))
    line = next(line for line in out.splitlines() if line.startswith("marble"))
    assert f"{total[0]:5.3f}" in line and f"{float(m.diffuse_mean_free_path[0]):6.2f}" in line
    for name in ("apple", "chicken1", "cream", "ketchup", "skin2", "wholemilk"):
        assert any(row.startswith(name) for row in out.splitlines())


def test_materials_total_of_another_profile(capsys):
    from sssjax import profiles

    assert main(["materials", "--profile", "pbd"]) == 0
    out = capsys.readouterr().out
    m = preset("skin1")
    total = np.asarray(profiles.Rd_total(m.sigma_a, m.sigmap_s, m.eta, "pbd"))
    classic = np.asarray(dipole.Rd_total(m.sigma_a, m.sigmap_s, m.eta))
    assert abs(total[1] - classic[1]) > 0.005  # the column really changes
    line = next(line for line in out.splitlines() if line.startswith("skin1"))
    assert f"{total[1]:5.3f}" in line and "total R_d of PBD" in out


def test_demo_writes_profile_plot_and_render(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--size", "24", "--spp", "1"]) == 0
    out = capsys.readouterr().out
    png = tmp_path / "rd_profiles.png"
    assert png.exists() and png.stat().st_size > 10_000
    assert str(png) in out
    for name in ("marble_cube.png", "marble_cube.exr"):
        assert str(tmp_path / name) in out
    img = read_image(tmp_path / "marble_cube.exr")
    assert img.shape == (24, 24, 3) and np.all(np.isfinite(img)) and img.max() > 0
    meta = read_metadata(tmp_path / "marble_cube.exr")
    assert meta["spp"] == 1 and "marble" in meta["media"]


def test_render_refuses_to_overwrite_its_scene(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SMALL)
    before = scene.read_text()
    assert main(["render", str(scene), "-o", str(tmp_path / "s.toml.png"), "-o", str(scene)]) == 2
    assert "s.toml" in capsys.readouterr().err
    assert scene.read_text() == before


def test_render_cli_writes_png_and_exr(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SMALL)
    png, exr = tmp_path / "o" / "a.png", tmp_path / "o" / "a.exr"
    assert main(["render", str(scene), "-o", str(png), "-o", str(exr), "--spp", "2"]) == 0
    assert png.exists() and exr.exists()
    assert read_metadata(exr)["spp"] == 2


def test_render_cli_bad_flag_value(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SMALL)
    assert main(["render", str(scene), "--spp", "0"]) == 2
    assert "--spp must be >= 1" in capsys.readouterr().err


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
