"""The parameter map (`sssjax.params`): names, values and roles of a scene's parameters,
applying values, resolving names, and its users (fit files, the command line)."""

from pathlib import Path

import numpy as np
import pytest

import sssjax
from sssjax.params import Enters, ParameterError, apply, parameters, resolve

ROOT = Path(__file__).resolve().parent.parent


def two_materials():
    return sssjax.load_scene(
        {
            "camera": {"origin": [0, 0, 50], "target": [0, 0, 0], "width": 8, "height": 8},
            "render": {"spp": 1, "light_samples": 1},
            "sss": {"cloud_size": 64},
            "lights": [
                {"type": "point", "position": [0, 30, 30], "intensity": [100.0, 90.0, 80.0]},
                {"type": "area", "corner": [-5, 20, -5], "edge_u": [10, 0, 0],
                 "edge_v": [0, 0, 10], "radiance": 2.0},
            ],
            "materials": {
                "wax": {"type": "translucent", "sigma_a": [0.1, 0.2, 0.3], "sigma_s": 2.0,
                        "g": 0.2, "eta": 1.4},
                "milk": {"type": "translucent", "preset": "skimmilk"},
            },
            "shapes": [
                {"type": "sphere", "material": "wax", "radius": 5.0, "translate": [-6, 0, 0]},
                {"type": "sphere", "material": "milk", "radius": 5.0, "translate": [6, 0, 0]},
            ],
        }
    )  # fmt: skip


def test_parameters_list_every_value_and_role():
    scene = two_materials()
    table = parameters(scene)
    names = [
        f"{m}.{f}" for m in ("wax", "milk") for f in ("sigma_a", "sigma_s", "sigmap_s", "g", "eta")
    ]
    assert list(table) == names + ["lights.0", "lights.1", "exposure"]
    np.testing.assert_allclose(table["wax.sigma_a"].value, [0.1, 0.2, 0.3], rtol=1e-6)
    np.testing.assert_allclose(table["wax.sigmap_s"].value, 2.0 * 0.8, rtol=1e-6)
    assert table["wax.eta"].value == pytest.approx(1.4)
    assert table["wax.g"].enters is Enters.SHADED and table["wax.eta"].enters is Enters.RETRACED
    assert table["lights.1"].enters is Enters.EMISSION and table["lights.1"].value == 1.0
    assert table["exposure"].enters is Enters.IMAGE


def test_apply_sets_values_and_reads_back():
    scene = two_materials()
    out = apply(scene, {"wax.g": 0.5, "wax.sigmap_s": [1.0, 2.0, 3.0], "milk.eta": 1.5,
                        "lights.1": 3.0})  # fmt: skip
    wax = out.media()["wax"]
    np.testing.assert_allclose(wax.sigma_s, np.array([1.0, 2.0, 3.0]) / (1 - 0.5), rtol=1e-6)
    np.testing.assert_allclose(wax.sigma_a, [0.1, 0.2, 0.3], rtol=1e-6)  # untouched
    assert float(out.media()["milk"].eta) == pytest.approx(1.5)
    np.testing.assert_array_equal(out.lights[1].radiance, 3.0 * scene.lights[1].radiance)
    np.testing.assert_array_equal(out.lights[0].intensity, scene.lights[0].intensity)
    back = parameters(out)
    np.testing.assert_allclose(back["wax.sigmap_s"].value, [1.0, 2.0, 3.0], rtol=1e-6)
    assert apply(scene, {}) == scene


@pytest.mark.slow
def test_emission_parameters_are_linear_in_the_image():
    """`lights.N` enters linearly: the image of a scene with one light at factor 2.5 is 2.5
    times the image of the scene."""
    scene = sssjax.load_scene(ROOT / "scenes" / "marble_cube.toml").with_settings(
        width=12, height=12, spp=1, sss_cloud_size=128, light_samples=1
    )
    a = np.asarray(sssjax.render(scene, 0), dtype=np.float64)
    b = np.asarray(sssjax.render(apply(scene, {"lights.0": 2.5}), 0), dtype=np.float64)
    assert a.max() > 0
    np.testing.assert_allclose(b, 2.5 * a, rtol=1e-5, atol=1e-7 * a.max())


@pytest.mark.parametrize(
    "names,message",
    [
        (["sigma_a"], "name the material"),
        (["wax.sigma_q"], "unknown parameter 'sigma_q'"),
        (["wood.sigma_a"], "no translucent material 'wood'"),
        (["wax.sigma_s", "wax.sigmap_s"], "not both"),
        (["wax.eta", "milk.eta", "wax.sigma_a"], "one material at a time"),
        (["lights.2"], r"no such light \(the scene has 2"),
        (["wax.sigma_a", "lights.0", "lights.1", "exposure"], "only their product"),
        (["exposure"], "at least one coefficient"),
    ],
)
def test_resolve_errors(names, message):
    with pytest.raises(ParameterError, match=message):
        resolve(two_materials(), names)


def test_resolve_defaults_and_order():
    got = [p.name for p in resolve(two_materials(), None)]
    assert got == ["wax.sigma_a", "wax.sigma_s", "milk.sigma_a", "milk.sigma_s"]
    got = [p.name for p in resolve(two_materials(), ["lights.1", "wax.g", "wax.g"])]
    assert got == ["lights.1", "wax.g"]


def test_fit_file_names_are_checked_when_read(tmp_path):
    from sssjax.fit import FitError, load_fit_file

    f = tmp_path / "f.toml"
    f.write_text(
        f'scene = "{ROOT / "scenes" / "marble_cube.toml"}"\nparams = ["marble.sigma_z"]\n'
        "[synthetic]\nseed = 1\n"
    )
    with pytest.raises(FitError, match=r"f.toml: params: unknown parameter 'sigma_z'"):
        load_fit_file(f)
    f.write_text(
        f'scene = "{ROOT / "scenes" / "marble_cube.toml"}"\n[synthetic]\nseed = 1\n'
        '[init]\n"wax.sigma_a" = 0.1\n'
    )
    with pytest.raises(FitError, match=r"\[init\]: parameter 'wax.sigma_a': no translucent"):
        load_fit_file(f)


def test_params_command_lists_the_parameters(capsys):
    from sssjax.cli import main

    assert main(["params", str(ROOT / "scenes" / "marble_cube.toml")]) == 0
    out = capsys.readouterr().out
    assert "marble.eta" in out and "retraced" in out and "lights.0" in out
    assert "0.0021 0.0041 0.0071" in out  # marble's sigma_a
