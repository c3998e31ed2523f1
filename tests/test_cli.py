"""The command line: tables, demo output, one-line errors."""

import numpy as np

from sssjax import dipole, preset
from sssjax.cli import main


def test_materials_prints_every_preset_with_derived_values(capsys):
    assert main(["materials"]) == 0
    out = capsys.readouterr().out
    m = preset("marble")
    total = np.asarray(dipole.Rd_total(m.sigma_a, m.sigmap_s, m.eta))
    line = next(line for line in out.splitlines() if line.startswith("marble"))
    assert f"{total[0]:5.3f}" in line and f"{float(m.diffuse_mean_free_path[0]):6.2f}" in line
    for name in ("apple", "chicken1", "cream", "ketchup", "skin2", "wholemilk"):
        assert any(row.startswith(name) for row in out.splitlines())


def test_demo_writes_profile_plot(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path)]) == 0
    png = tmp_path / "rd_profiles.png"
    assert png.exists() and png.stat().st_size > 10_000
    assert str(png) in capsys.readouterr().out
