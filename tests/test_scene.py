"""Scene loading: every bad scene in tests/data/bad_scenes gives its one promised message."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sssjax import preset
from sssjax.scene import SceneError, load_scene

BAD = sorted((Path(__file__).parent / "data" / "bad_scenes").glob("*.toml"))
SCENES = sorted((Path(__file__).parent.parent / "scenes").glob("*.toml"))


def expected(path: Path) -> str:
    first = path.read_text().splitlines()[0]
    assert first.startswith("# expect: ")
    return first[len("# expect: ") :]


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_scene_message(path):
    with pytest.raises(SceneError) as e:
        load_scene(path)
    msg = str(e.value)
    assert msg.startswith(str(path)), msg  # names the file
    assert expected(path) in msg
    assert "\n" not in msg  # one line


def test_bad_scene_cli_exits_nonzero_without_traceback(tmp_path):
    path = Path(__file__).parent / "data" / "bad_scenes" / "negative_radius.toml"
    p = subprocess.run(
        [sys.executable, "-m", "sssjax", "render", str(path), "-o", str(tmp_path / "x.png")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2
    assert "Traceback" not in p.stderr
    assert p.stderr.strip().count("\n") == 0
    assert "radius: must be > 0, got -2" in p.stderr
    assert not (tmp_path / "x.png").exists()


def test_missing_scene_file(tmp_path):
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "nope.toml")


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_shipped_scenes_load(path):
    scene = load_scene(path)
    assert scene.shapes and scene.lights


def test_dict_scene_and_defaults():
    scene = load_scene(
        {
            "camera": {"origin": [0, 0, 10], "target": [0, 0, 0]},
            "materials": {"m": {"type": "translucent", "preset": "Ketchup", "scale": 2.0}},
            "shapes": [{"type": "sphere", "material": "m", "radius": 1.0}],
            "lights": [{"type": "point", "position": [0, 5, 5], "intensity": [1, 1, 1]}],
        }
    )
    assert scene.camera.width == 256 and scene.render.spp == 16
    med = scene.media()["m"]
    np.testing.assert_allclose(med.sigma_a, 2 * np.asarray(preset("ketchup").sigma_a), rtol=1e-6)
    assert scene.translucent_materials == ["m"]


def test_dict_scene_takes_numpy_and_jax_numbers():
    """A scene dict built from arrays (a fit's result, a parameter sweep) loads as its plain
    numbers would, and its values are still validated."""
    import jax.numpy as jnp

    def scene(sigma_a, radius):
        return {
            "camera": {"origin": np.array([0.0, 0.0, 10.0]), "target": [0, 0, 0], "width": 8},
            "materials": {"m": {"type": "translucent", "sigma_a": sigma_a, "sigma_s": 1.0}},
            "shapes": [{"type": "sphere", "material": "m", "radius": radius}],
        }

    sc = load_scene(scene(np.float32([0.0021, 0.0041, 0.0071]), jnp.float32(1.5)))
    np.testing.assert_allclose(sc.media()["m"].sigma_a, [0.0021, 0.0041, 0.0071], rtol=1e-7)
    assert sc.camera.width == 8 and sc.source["shapes"][0]["radius"] == 1.5
    assert load_scene(scene([np.float64(0.1)] * 3, 1)).media()["m"].sigma_a[0] == 0.1
    with pytest.raises(SceneError, match=r"sigma_a: must be >= 0, got \[0.1, -0.2, 0.3\]"):
        load_scene(scene(np.array([0.1, -0.2, 0.3]), 1.0))
    with pytest.raises(SceneError, match="radius: must be finite, got nan"):
        load_scene(scene(0.1, np.float32("nan")))


def test_tabulated_profile_beyond_its_eta_range_warns():
    """The table covers eta 1.0-1.6; beyond it the diffusion transport holds the profile at
    its edge, which a scene must say (the volumetric transport and other profiles do not
    use the table)."""
    from sssjax.scene import SceneWarning

    def scene(eta, **sss):
        return {
            "camera": {"origin": [0, 0, 10], "target": [0, 0, 0]},
            "sss": sss,
            "materials": {"m": {"type": "translucent", "preset": "marble", "eta": eta}},
            "shapes": [{"type": "sphere", "material": "m", "radius": 1.0}],
            "lights": [{"type": "point", "position": [0, 5, 5], "intensity": 1.0}],
        }

    msg = r"\[materials.m\] eta = 1.8 is outside the tabulated profile's range 1.0-1.6"
    with pytest.warns(SceneWarning, match=msg):
        load_scene(scene(1.8, profile="tabulated"))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scene(scene(1.5, profile="tabulated"))
        load_scene(scene(1.8, profile="better_dipole"))
        load_scene(scene(1.8, profile="tabulated", transport="volumetric"))


def test_sigmap_s_and_g_in_scene():
    scene = load_scene(
        {
            "camera": {"origin": [0, 0, 10], "target": [0, 0, 0]},
            "materials": {"m": {"type": "translucent", "sigma_a": 0.1, "sigmap_s": 1.0, "g": 0.5}},
            "shapes": [{"type": "sphere", "material": "m", "radius": 1.0}],
        }
    )
    med = scene.media()["m"]
    np.testing.assert_allclose(med.sigma_s, 2.0, rtol=1e-6)
    np.testing.assert_allclose(med.sigmap_s, 1.0, rtol=1e-6)


def test_sss_profile_setting():
    base = {
        "camera": {"origin": [0, 0, 10], "target": [0, 0, 0]},
        "materials": {"m": {"type": "translucent", "preset": "marble"}},
        "shapes": [{"type": "sphere", "material": "m", "radius": 1.0}],
    }
    assert load_scene(base).sss.profile == "dipole"  # the default
    for name in ("dipole", "better_dipole", "pbd", "tabulated"):
        assert load_scene({**base, "sss": {"profile": name}}).sss.profile == name
    scene = load_scene(base).with_settings(sss_profile="pbd")
    assert scene.sss.profile == "pbd"
    with pytest.raises(ValueError, match="did you mean 'pbd'"):
        load_scene(base).with_settings(sss_profile="pdb")
    with pytest.raises(SceneError, match=r"\[sss\] profile: expected a string, got 3"):
        load_scene({**base, "sss": {"profile": 3}})


# --- the scene writer: load(dump(scene)) == scene -----------------------------------------
def every_feature(tmp_path: Path) -> dict:
    """A scene dict with every shape, light and material kind, an OBJ mesh (relative path),
    an orthographic camera and non-default settings."""
    (tmp_path / "meshes").mkdir(parents=True)
    (tmp_path / "meshes" / "tet.obj").write_text(
        "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 10\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    )
    return {
        "camera": {
            "origin": [0.0, 50.0, 0.0],
            "target": [0.0, 0.0, 0.0],
            "up": [0.0, 0.0, -1.0],
            "projection": "orthographic",
            "view_width": 60.0,
            "width": 24,
            "height": 16,
        },
        "render": {"spp": 9, "light_samples": 3, "max_depth": 2, "seed": 7, "tile": 8},
        "sss": {"strategy": "annulus", "inner": 0.5, "outer": 3.25, "profile": "pbd"},
        "lights": [
            {
                "type": "area",
                "corner": [-5, 40, -5],
                "edge_u": [10, 0, 0],
                "edge_v": [0, 0, 10],
                "radiance": [1.0, 2.0, 3.5],
            },
            {"type": "point", "position": [10, 30, 10], "intensity": 1e3},
            {
                "type": "beam",
                "position": [1, 50, 2],
                "direction": [0.3, -1.0, 0.2],
                "radius": 0.1,
                "power": [1.0, 0.5, 0.25],
            },
        ],
        "materials": {
            "milk": {
                "type": "translucent",
                "preset": "skimmilk",
                "scale": [1.0, 2.0, 0.5],
                "eta": 1.41,
            },
            "wax": {"type": "translucent", "sigma_a": 0.013, "sigmap_s": 1.7, "g": 0.35},
            "red": {"type": "diffuse", "albedo": [0.6, 0.1, 0.1]},
            "glass": {"type": "mirror", "reflectance": 0.9},
        },
        "shapes": [
            {"type": "sphere", "material": "milk", "radius": 3.3, "translate": [1, 2, 3]},
            {"type": "cube", "material": "red", "size": [1.0, 2.0, 3.0], "rotate": [10, 20, 30]},
            {"type": "cylinder", "material": "wax", "radius": 2.0, "height": 5.5, "scale": 1.5},
            {"type": "cone", "material": "glass", "radius": 1.0, "height": 2.0},
            {
                "type": "quadmesh",
                "material": "red",
                "vertices": [[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]],
                "faces": [[0, 1, 2, 3]],
                "scale": [2.0, 1.0, 3.0],
            },
            {"type": "quadmesh", "material": "wax", "file": "meshes/tet.obj"},
        ],
    }


def test_dump_scene_round_trips(tmp_path):
    from sssjax.scene import dump_scene

    src = every_feature(tmp_path)
    scene = load_scene(src, base_dir=tmp_path)
    scenes = [scene] + [load_scene(p) for p in SCENES]
    for i, sc in enumerate(scenes):
        path = tmp_path / "out" / f"s{i}.toml"
        path.parent.mkdir(exist_ok=True)
        text = sc.to_toml(path)
        assert path.read_text() == text
        back = load_scene(path)  # from another folder: the OBJ path was made absolute
        assert back == sc, sc.path
        assert hash(back) == hash(sc)
        assert back.to_toml().split("\n", 1)[1] == text.split("\n", 1)[1]  # a fixed point
    with pytest.raises(FileExistsError):
        dump_scene(scene, tmp_path / "out" / "s0.toml")  # never overwrites
    # equality can fail: a setting, a medium, a light or a shape's size differs
    assert scene.with_settings(spp=4) != scene
    src["materials"]["wax"]["g"] = 0.36
    assert load_scene(src, base_dir=tmp_path) != scene
    src = every_feature(tmp_path / "again")
    src["lights"][2]["radius"] = 0.2
    assert load_scene(src, base_dir=tmp_path / "again") != scene
    src = every_feature(tmp_path / "once_more")
    src["shapes"][0]["radius"] = 3.4
    assert load_scene(src, base_dir=tmp_path / "once_more") != scene
