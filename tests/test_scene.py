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
    for name in ("dipole", "better_dipole", "pbd"):
        assert load_scene({**base, "sss": {"profile": name}}).sss.profile == name
    scene = load_scene(base).with_settings(sss_profile="pbd")
    assert scene.sss.profile == "pbd"
    with pytest.raises(ValueError, match="did you mean 'pbd'"):
        load_scene(base).with_settings(sss_profile="pdb")
    with pytest.raises(SceneError, match=r"\[sss\] profile: expected a string, got 3"):
        load_scene({**base, "sss": {"profile": 3}})
