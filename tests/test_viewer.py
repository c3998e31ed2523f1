"""The browser previewer (`sssjax preview`): server, scene nodes, GUI actions, a real browser.

The browser test drives Debian's headless Chromium through its DevTools protocol (a websocket,
no extra packages) and needs `/usr/bin/chromium`; `make test` installs it when missing.
"""

from __future__ import annotations

import base64
import io
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from sssjax import load_scene
from sssjax.camera import camera_rays
from sssjax.imageio import read_image, srgb_encode
from sssjax.raytree import RayTree
from sssjax.viewer import (
    RAY_COLORS,
    Previewer,
    camera_wxyz,
    merge_trees,
    save_paths,
    scene_meshes,
)

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
CHROMIUM = "/usr/bin/chromium"


@dataclass
class FakeView:
    """What viser's `client.camera` offers, without a browser."""

    position: tuple
    look_at: tuple
    up_direction: tuple
    fov: float  # radians, vertical
    aspect: float


@pytest.fixture(scope="module")
def cube():
    p = Previewer(SCENES / "marble_cube.toml", port=0).start()
    yield p
    p.stop()


@pytest.fixture(scope="module")
def prims():
    p = Previewer(SCENES / "primitives.toml", port=0).start()
    yield p
    p.stop()


def _mesh_area(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def _glb_mesh(glb: bytes):
    import trimesh

    scene = trimesh.load(io.BytesIO(glb), file_type="glb")
    (geom,) = scene.geometry.values()
    return geom


# --- server and scene nodes -------------------------------------------------------------
def test_serves_page_and_stops(cube):
    assert cube.url.startswith("http://127.0.0.1:")
    with urllib.request.urlopen(cube.url, timeout=10) as r:
        assert r.status == 200
        body = r.read()
    assert b"<html" in body.lower() and b"<script" in body.lower()

    p = Previewer(SCENES / "marble_cube.toml", port=0).start()
    url = p.url
    assert urllib.request.urlopen(url, timeout=10).status == 200
    p.stop()
    with pytest.raises((urllib.error.URLError, ConnectionError)):
        urllib.request.urlopen(url, timeout=5)
    p.stop()  # idempotent


def test_scene_nodes_marble_cube(cube):
    names = set(cube.nodes)
    assert {n for n in names if n.startswith("/shapes/")} == {
        "/shapes/0_cube_marble",
        "/shapes/1_quadmesh_floor",
    }
    assert {n for n in names if n.startswith("/lights/")} == {"/lights/0_area"}
    assert "/camera/scene" in names
    for name, h in cube.nodes.items():
        assert h.name == name
    # the marble tint is its total diffuse reflectance, computed here from Jensen et al.'s
    # closed form with the measured marble coefficients (sigma'_s, sigma_a in 1/mm, eta 1.3)
    sp, sa, eta = np.array([2.19, 2.62, 3.00]), np.array([0.0021, 0.0041, 0.0071]), 1.3
    fdr = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    A = (1 + fdr) / (1 - fdr)
    ap = sp / (sp + sa)
    root = np.sqrt(3 * (1 - ap))
    total = ap / 2 * (1 + np.exp(-4 / 3 * A * root)) * np.exp(-root)  # about 0.87, 0.84, 0.80
    color = np.asarray(cube.nodes["/shapes/0_cube_marble"].color) / 255.0
    np.testing.assert_allclose(color, total, atol=0.5 / 255 + 1e-9)
    np.testing.assert_allclose(
        np.asarray(cube.nodes["/shapes/1_quadmesh_floor"].color) / 255.0,
        [0.35, 0.35, 0.38],
        atol=0.003,
    )
    # the cube is a 20 mm cube centred at (0, 10, 0): exact area and bounds
    h = cube.nodes["/shapes/0_cube_marble"]
    v, f = np.asarray(h.vertices, dtype=np.float64), np.asarray(h.faces)
    assert _mesh_area(v, f) == pytest.approx(6 * 20.0**2, rel=1e-6)
    np.testing.assert_allclose(v.min(0), [-10, 0, -10], atol=1e-5)
    np.testing.assert_allclose(v.max(0), [10, 20, 10], atol=1e-5)
    # the area light: an emissive 30 x 30 mm square at y = 80, wound to face down
    light = _glb_mesh(cube.nodes["/lights/0_area"].glb_data)
    assert light.area == pytest.approx(900.0, rel=1e-6)
    np.testing.assert_allclose(light.vertices[:, 1], 80.0)
    n = light.face_normals
    np.testing.assert_allclose(n, np.tile([0.0, -1.0, 0.0], (len(n), 1)), atol=1e-6)
    assert np.min(light.visual.material.emissiveFactor) > 0.5


def test_scene_nodes_primitives(prims):
    scene = prims.scene
    shapes = sorted(n for n in prims.nodes if n.startswith("/shapes/"))
    assert shapes == [
        "/shapes/0_sphere_marble",
        "/shapes/1_cube_red",
        "/shapes/2_cylinder_skin",
        "/shapes/3_cone_potato",
        "/shapes/4_quadmesh_mirror",
        "/shapes/5_quadmesh_floor",
    ]
    for spec, name in zip(scene.shapes, shapes, strict=True):
        h = prims.nodes[name]
        if spec.material == "mirror":
            mesh = _glb_mesh(h.glb_data)  # drawn as polished metal
            v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
            assert mesh.visual.material.metallicFactor == 1.0
            assert mesh.visual.material.roughnessFactor <= 0.1
        else:
            v, f = np.asarray(h.vertices, dtype=np.float64), np.asarray(h.faces)
        # the tessellation is the tracer's shape: area within tessellation error, and its
        # bounding box inside the exact one, touching it within 1 %
        exact = float(spec.shape.area())
        assert _mesh_area(v, f) == pytest.approx(exact, rel=0.01), name
        lo, hi = spec.shape.bounds()
        size = float(np.linalg.norm(hi - lo))
        assert np.all(v.min(0) >= lo - 1e-3) and np.all(v.max(0) <= hi + 1e-3), name
        np.testing.assert_allclose(v.min(0), lo, atol=0.01 * size)
        np.testing.assert_allclose(v.max(0), hi, atol=0.01 * size)
    red = np.asarray(prims.nodes["/shapes/1_cube_red"].color) / 255.0
    np.testing.assert_allclose(red, [0.6, 0.12, 0.1], atol=0.003)


def test_frustum_is_the_scene_camera(prims):
    from viser import transforms as vtf

    cam = prims.scene.camera
    h = prims.nodes["/camera/scene"]
    np.testing.assert_allclose(h.position, cam.origin, atol=1e-4)
    R = vtf.SO3(np.asarray(h.wxyz)).as_matrix()  # OpenCV: columns right, down, forward
    fwd = (cam.target - cam.origin) / np.linalg.norm(cam.target - cam.origin)
    np.testing.assert_allclose(R[:, 2], fwd, atol=1e-6)
    assert R[:, 1] @ cam.up < 0  # image "down" points against the scene's up
    assert h.fov == pytest.approx(math.radians(cam.fov))
    assert h.aspect == pytest.approx(cam.width / cam.height)
    np.testing.assert_allclose(camera_wxyz(cam), h.wxyz)


# --- GUI actions, headless --------------------------------------------------------------
def test_use_this_view(prims):
    view = FakeView((100.0, 50.0, 80.0), (0.0, 5.0, 0.0), (0.0, 1.0, 0.0), math.radians(50.0), 1.5)
    cam = prims.use_view(view, height=16)
    assert (cam.width, cam.height) == (24, 16)
    assert "/camera/render" in prims.nodes
    np.testing.assert_allclose(prims.nodes["/camera/render"].position, view.position, atol=1e-4)

    def ray(x, y, jx=0.0):
        pix = jnp.asarray([y * cam.width + x])
        jit = jnp.asarray([[[jx, 0.0]]])
        return np.asarray(camera_rays(cam, pix, jit)[1][0, 0], dtype=np.float64)

    want = np.subtract(view.look_at, view.position)
    want /= np.linalg.norm(want)
    np.testing.assert_allclose(ray(12, 8), want, atol=1e-5)  # the centre ray looks at look_at
    # top edge: half the vertical fov off axis; right edge: tan scaled by the aspect
    assert math.degrees(math.acos(ray(12, 0) @ want)) == pytest.approx(25.0, abs=1e-3)
    side = math.atan(math.tan(math.radians(25.0)) * 1.5)
    assert math.acos(np.clip(ray(23, 8, jx=1.0) @ want, -1, 1)) == pytest.approx(side, abs=1e-5)
    assert ray(12, 0)[1] > want[1]  # y = 0 is the top: up in the world

    with pytest.raises(ValueError, match="parallel"):
        prims.use_view(FakeView((0, 50, 0), (0, 0, 0), (0, 1, 0), 0.8, 1.0), height=16)
    assert prims.camera is cam  # a bad view leaves the camera as it was

    # clicking the drawn image picks the pixel whose ray goes through the click point
    for x, y in [(3, 11), (20, 2)]:
        pix = jnp.asarray([y * cam.width + x])
        o, d = camera_rays(cam, pix, jnp.asarray([[[0.5, 0.5]]]))
        eye = np.asarray(view.position) + np.array([-30.0, 40.0, 10.0])  # another viewpoint
        centre, _ = prims.image_plane()
        hit = np.asarray(o[0, 0]) + np.asarray(d[0, 0]) * (
            (centre - np.asarray(o[0, 0])) @ want / (np.asarray(d[0, 0]) @ want)
        )
        assert prims.pixel_at(eye, hit - eye) == (x, y)
    assert prims.pixel_at(view.position, -want) is None  # behind the camera


@pytest.mark.slow
def test_render_and_save_never_overwrites(cube, tmp_path):
    view = FakeView((60.0, 40.0, 90.0), (0.0, 8.0, 0.0), (0.0, 1.0, 0.0), math.radians(40.0), 1.0)
    cam = cube.use_view(view, height=16)
    cube.controls["spp"].value = 1
    cube.controls["light_samples"].value = 1
    cube.controls["sss"].value = False  # the SSS switch (its compile would double the time)
    assert cube.render_scene().sss.enabled is False
    rs = cube.render_scene()
    assert rs is cube.render_scene()  # reused while nothing changes (compiled renderer)
    np.testing.assert_allclose(rs.camera.origin, cam.origin)
    assert (rs.camera.width, rs.camera.height, rs.render.spp, rs.render.light_samples) == (
        16,
        16,
        1,
        1,
    )
    with pytest.raises(ValueError, match="Render first"):
        cube.save(tmp_path / "early")
    image = cube.render()
    assert image.shape == (16, 16, 3)
    assert np.all(np.isfinite(image)) and np.all(image >= 0) and image.mean() > 0.01
    assert cube.controls["progress"].value == 100.0
    assert cube.image_handle.image.shape == (16, 16, 3)  # shown in the panel
    assert "/render_image" in cube.nodes  # and on the image plane in 3D

    # the ray tree of a pixel is that of this render: its radiance is the rendered pixel's
    tree = cube.show_raytree((8, 9))
    assert tree.counts()["camera"] == 1  # spp 1
    np.testing.assert_allclose(tree.radiance, image[9, 8], rtol=2e-3, atol=1e-5)
    cam_node = cube.nodes["/raytree/camera"]
    np.testing.assert_allclose(cam_node.points[0, 0], cam.origin, atol=1e-3)
    with pytest.raises(ValueError, match="outside"):
        cube.show_raytree((16, 0))

    scene_bytes = (SCENES / "marble_cube.toml").read_bytes()
    first = cube.save(tmp_path / "view")
    assert {p.name for p in first.values()} == {"view.png", "view.exr", "view.toml"}
    first_bytes = {k: p.read_bytes() for k, p in first.items()}
    saved = load_scene(first["toml"])
    for field in ("origin", "target", "up"):
        np.testing.assert_allclose(getattr(saved.camera, field), getattr(cam, field))
    assert (saved.camera.fov, saved.camera.width, saved.camera.height) == (cam.fov, 16, 16)
    assert (saved.render.spp, saved.render.light_samples) == (1, 1)
    assert saved.sss.enabled is False
    assert len(saved.shapes) == len(cube.scene.shapes)
    np.testing.assert_allclose(read_image(first["exr"]), image, rtol=1e-6)

    second = cube.save(tmp_path / "view.png")  # same stem again: a new name
    assert {p.name for p in second.values()} == {"view_1.png", "view_1.exr", "view_1.toml"}
    assert {k: p.read_bytes() for k, p in first.items()} == first_bytes
    (tmp_path / "other.exr").write_bytes(b"precious")  # any existing file blocks a stem
    third = cube.save(tmp_path / "other")
    assert third["png"].name == "other_1.png"
    assert (tmp_path / "other.exr").read_bytes() == b"precious"
    assert (SCENES / "marble_cube.toml").read_bytes() == scene_bytes
    # a new view after the render: the image and the saved camera stay those of the render
    cube.use_view(FakeView((0.0, 90.0, 60.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 0.5, 2.0), 8)
    assert "/render_image" not in cube.nodes
    later = load_scene(cube.save(tmp_path / "later")["toml"])
    np.testing.assert_allclose(later.camera.origin, cam.origin)
    assert (later.camera.width, later.camera.height) == (16, 16)
    protected = tmp_path / "mine.toml"
    protected.write_text("x")
    assert save_paths(tmp_path / "mine")["toml"].name == "mine_1.toml"


def test_transport_dropdown_renders_traces_and_saves_the_volumetric_walks(cube, tmp_path):
    """The panel's transport: "volumetric" renders the cube's random walks (a pixel's ray
    tree holds walk segments and recomputes its rendered radiance), and the saved scene
    file keeps the transport, so `sssjax render` of it renders what the panel showed."""
    view = FakeView((60.0, 40.0, 90.0), (0.0, 8.0, 0.0), (0.0, 1.0, 0.0), math.radians(30.0), 1.0)
    cube.use_view(view, height=8)
    c = cube.controls
    assert c["transport"].value == "diffusion"  # the scene's
    c["spp"].value, c["light_samples"].value, c["sss"].value = 2, 1, True
    c["transport"].value = "volumetric"
    assert cube.render_scene().sss.transport == "volumetric"
    image = cube.render()
    assert np.all(np.isfinite(image)) and image[3, 4].mean() > 0.01  # the cube's top
    tree = cube.show_raytree((4, 3))
    assert tree.counts()["walk"] > 0
    np.testing.assert_allclose(tree.radiance, image[3, 4], rtol=2e-3, atol=1e-5)
    saved = load_scene(cube.save(tmp_path / "walks")["toml"])
    assert saved.sss.transport == "volumetric" and saved.render.spp == 2
    c["transport"].value = "diffusion"
    assert cube.render_scene().sss.transport == "diffusion"


def test_opacity_slider(prims):
    prims.controls["opacity"].value = 0.3  # as the browser's slider does
    for m in scene_meshes(prims.scene, prims.resolution):
        if m.style == "matte":
            assert prims.nodes[m.name].opacity == pytest.approx(0.3)
        elif m.style == "mirror":
            mat = _glb_mesh(prims.nodes[m.name].glb_data).visual.material
            assert mat.baseColorFactor[3] == pytest.approx(0.3 * 255, abs=1)
    prims.controls["opacity"].value = 1.0
    assert prims.nodes["/shapes/1_cube_red"].opacity is None


def _tree(shift: float = 0.0, spp: int = 2) -> RayTree:
    """A hand-made tree: 2 camera rays, 1 reflection, 3 lit shadow rays, one single-scattering
    path, and 5 dipole points."""
    kind = np.array([0, 0, 1, 2, 2, 2, 4, 5])
    n = len(kind)
    origin = np.arange(n * 3, dtype=float).reshape(n, 3) + shift
    end = origin + np.array([0.0, 1.0, 0.0])
    return RayTree(
        pixel=(3, 4),
        spp=spp,
        radiance=np.array([0.1, 0.2, 0.3]) + shift,
        origin=origin,
        end=end,
        kind=kind,
        depth=np.array([0, 0, 1, 0, 1, 0, 0, 0]),
        sample=np.array([0, 1, 1, 0, 1, 1, 0, 0]),
        parent=np.array([-1, -1, 1, 0, 2, 1, 0, 6]),
        miss=np.zeros(n, bool),
        points=np.arange(15, dtype=float).reshape(5, 3),
        point_weight=np.array([1.0, 0.5, 0.001, 0.0, 0.2]),
        point_sample=np.array([0, 0, 1, 1, 1]),
    )


def test_raytree_drawing_and_toggles(prims):
    from sssjax.raytree import COLORS

    # the same colours as the pictures of `sssjax raytree`
    for kind, hexc in COLORS.items():
        assert "#{:02x}{:02x}{:02x}".format(*RAY_COLORS[kind]) == hexc
    tree = _tree()
    prims.draw_raytree(tree)
    drawn = {n for n in prims.nodes if n.startswith("/raytree/")}
    assert drawn == {
        "/raytree/camera",
        "/raytree/reflected",
        "/raytree/shadow",
        "/raytree/ss_refracted",
        "/raytree/ss_light",
        "/raytree/dipole/points1",
        "/raytree/dipole/points2",
        "/raytree/dipole/points3",
    }
    shadow = prims.nodes["/raytree/shadow"]
    np.testing.assert_allclose(shadow.points[:, 0], tree.origin[3:6], atol=1e-5)
    np.testing.assert_allclose(shadow.points[:, 1], tree.end[3:6], atol=1e-5)
    assert tuple(np.asarray(shadow.colors).reshape(-1, 3)[0]) == RAY_COLORS["shadow"]
    assert tuple(np.asarray(prims.nodes["/raytree/camera"].colors).reshape(-1, 3)[0]) == (255,) * 3
    # points sized by weight: 1.0 -> largest class, 0.5, 0.2 smaller; 0.001 and 0 not drawn
    sizes = [prims.nodes[f"/raytree/dipole/points{b}"].point_size for b in (1, 2, 3)]
    assert sizes[0] < sizes[1] < sizes[2]
    np.testing.assert_allclose(prims.nodes["/raytree/dipole/points3"].points, [[0, 1, 2]])
    legend = prims.controls["legend"].content
    assert ">3</td>" in legend and "3 of 4" in legend
    prims.controls["show_shadow"].value = False  # the toggle of a kind
    assert prims.nodes["/raytree/shadow"].visible is False
    assert prims.nodes["/raytree/camera"].visible is True
    prims.controls["show_dipole"].value = False
    assert not any(prims.nodes[f"/raytree/dipole/points{b}"].visible for b in (1, 2, 3))
    prims.controls["show_shadow"].value = True
    prims.controls["show_dipole"].value = True
    prims.draw_raytree(_tree(spp=1))  # a new tree replaces the old one
    assert sum(n.startswith("/raytree/") for n in prims.nodes) == 8


def test_merge_trees_of_passes():
    a, b = _tree(0.0), _tree(100.0)
    m = merge_trees([a, b])
    assert m.spp == 4 and len(m.kind) == 16 and len(m.points) == 10
    np.testing.assert_array_equal(m.sample, np.concatenate([a.sample, b.sample + 2]))
    np.testing.assert_array_equal(
        m.point_sample, np.concatenate([a.point_sample, b.point_sample + 2])
    )
    # parents still point at the segment whose end the child starts from
    child = m.parent >= 0
    np.testing.assert_array_equal(
        m.origin[child][:, 0] // 100, m.origin[m.parent[child]][:, 0] // 100
    )
    np.testing.assert_array_equal(m.parent[8:][b.parent >= 0], b.parent[b.parent >= 0] + 8)
    np.testing.assert_allclose(m.radiance, (a.radiance + b.radiance) / 2)
    assert merge_trees([a]) is a


# --- the command line -------------------------------------------------------------------
def test_preview_command_prints_url_and_stops_on_ctrl_c():
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sssjax",
            "preview",
            str(SCENES / "marble_cube.toml"),
            "--port",
            "0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        # pytest-xdist workers ignore SIGINT, and an ignored signal is inherited: give the
        # command the default Ctrl-C a terminal would
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    lines: list[str] = []
    # drain the output in a thread: a child blocked on a full pipe could not exit
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        url, t0 = None, time.time()
        while url is None and time.time() - t0 < 60:
            url = next(
                (ln.split("open ", 1)[1].split()[0] for ln in lines if "open http://" in ln), None
            )
            time.sleep(0.05)
        assert url is not None and url.startswith("http://127.0.0.1:"), lines
        assert urllib.request.urlopen(url, timeout=10).status == 200
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=60)  # generous: CI machines are loaded
        except subprocess.TimeoutExpired:
            rc = None
        assert rc == 0, "".join(lines[-30:])
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_preview_command_bad_scene(tmp_path, capsys):
    from sssjax.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\norigin = [0, 0, 1]\ntarget = [0, 0, 0]\nfov = -3\n")
    assert main(["preview", str(bad), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "fov" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


# --- a real browser ---------------------------------------------------------------------
def _decode_png(data: bytes) -> np.ndarray:
    """sRGB 0-255 pixels of a PNG."""
    with tempfile.NamedTemporaryFile(suffix=".png") as f:
        f.write(data)
        f.flush()
        linear = read_image(f.name)
    return np.rint(srgb_encode(np.clip(linear, 0, 1)) * 255.0)


_FRAMES = """new Promise(done => {
  let n = 0;
  const step = () => (++n >= 4 ? done(n) : requestAnimationFrame(step));
  requestAnimationFrame(step);
})"""


def browser_screenshot(
    url: str, ready, size=(1100, 760), timeout: float = 90.0, then=None
) -> bytes:
    """A PNG screenshot of `url` in headless Chromium, taken once `ready()` holds and two
    consecutive screenshots agree (the WebGL canvas has settled). Uses the DevTools protocol
    over a websocket (`websockets` comes with viser). `then(evaluate)`, if given, runs after
    the screenshot while the page is still open; `evaluate(js)` returns the expression's
    value."""
    import websockets.sync.client as wsc

    user_dir = tempfile.mkdtemp(prefix="sssjax-chromium-")
    args = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--use-angle=swiftshader",  # software WebGL
        "--enable-unsafe-swiftshader",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--hide-scrollbars",
        "--remote-debugging-port=0",
        f"--user-data-dir={user_dir}",
        f"--window-size={size[0]},{size[1]}",
        url,
    ]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.time()

    def waited():
        assert time.time() - t0 < timeout, "headless chromium timed out"
        assert proc.poll() is None, f"chromium exited with status {proc.returncode}"
        time.sleep(0.2)

    try:
        port_file = Path(user_dir) / "DevToolsActivePort"
        while not (port_file.exists() and len(port_file.read_text().split()) >= 2):
            waited()
        port = int(port_file.read_text().split()[0])
        pages = []
        while not pages:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                pages = [t for t in json.load(r) if t["type"] == "page"]
            if not pages:
                waited()
        while not ready():
            waited()
        with wsc.connect(pages[0]["webSocketDebuggerUrl"], max_size=None) as ws:
            n = 0

            def call(method, **params):
                nonlocal n
                n += 1
                ws.send(json.dumps({"id": n, "method": method, "params": params}))
                while True:
                    msg = json.loads(ws.recv(timeout=timeout))
                    if msg.get("id") == n:
                        assert "result" in msg, msg
                        return msg["result"]

            prev = None
            while True:
                # the client warns about software WebGL in a toast: not part of the scene
                call(
                    "Runtime.evaluate",
                    expression="document.querySelectorAll('.mantine-Notification-root')"
                    ".forEach(e => e.remove())",
                )
                # let the page draw a few new frames, so that no screenshot is a stale frame
                call("Runtime.evaluate", expression=_FRAMES, awaitPromise=True)
                png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
                img = _decode_png(png)
                if prev is not None and prev.shape == img.shape and np.abs(img - prev).mean() < 0.5:
                    title = call("Runtime.evaluate", expression="document.title")["result"]["value"]
                    assert title == "Viser", f"not the viewer page: {title!r}"
                    if then is not None:
                        then(
                            lambda js: call("Runtime.evaluate", expression=js, returnByValue=True)[
                                "result"
                            ]["value"]
                        )
                    return png
                prev = img
                waited()
                time.sleep(0.8)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(user_dir, ignore_errors=True)


def test_browser_shows_the_scene(tmp_path):
    assert os.access(CHROMIUM, os.X_OK), "needs Debian's chromium (make test installs it)"
    p = Previewer(SCENES / "primitives.toml", port=0).start()
    before = p.camera
    ic = p.server.initial_camera  # the view the page opens with
    eye, centre = np.array(ic.position), np.array(ic.look_at)
    clicked = {}

    def use_this_view(evaluate):
        # press "Use this view" in the page: the browser's camera becomes the render camera
        clicked["size"] = evaluate("[window.innerWidth, window.innerHeight]")
        found = evaluate(
            "(() => { const b = [...document.querySelectorAll('button')]"
            ".find(b => b.textContent.trim() === 'Use this view');"
            " if (b) b.click(); return !!b; })()"
        )
        assert found is True
        t0 = time.time()
        while p.camera is before and time.time() - t0 < 20:
            time.sleep(0.1)

    try:
        png = browser_screenshot(
            p.url, ready=lambda: len(p.server.get_clients()) > 0, then=use_this_view
        )
    finally:
        p.stop()
    cam = p.camera
    assert cam is not before, "the click on 'Use this view' did not reach the server"
    np.testing.assert_allclose(cam.origin, eye, atol=0.05)  # where the page looked from
    np.testing.assert_allclose(cam.target, centre, atol=0.05)
    assert cam.fov == pytest.approx(35.0, abs=0.01)  # the scene's fov, given to the page
    assert cam.height == 240  # the panel's "Height (px)"
    w_px, h_px = clicked["size"]
    assert cam.width / cam.height == pytest.approx(w_px / h_px, rel=0.01)
    out = tmp_path / "preview.png"
    out.write_bytes(png)
    img = _decode_png(png)
    h, w, _ = img.shape
    canvas = img[:, : int(w * 0.7)]  # the GUI panel floats on the right
    r, g, b = (canvas[..., k] for k in range(3))
    assert canvas.std() > 15, "blank canvas"
    colours = {tuple(c) for c in (canvas.reshape(-1, 3) // 16).astype(int)}
    assert len(colours) > 25, f"only {len(colours)} distinct colours"
    # the red diffuse cube (albedo 0.6, 0.12, 0.1) is drawn in red
    red = (r > 140) & (r > 2.0 * g) & (r > 2.0 * b)
    assert red.sum() > 300, f"{red.sum()} red pixels"
    # the grey floor (albedo 0.4) fills much of the view
    grey = (np.abs(r - g) < 12) & (np.abs(g - b) < 15) & (r > 60) & (r < 230)
    assert grey.mean() > 0.3, f"{grey.mean():.2f} of the canvas is grey floor"
