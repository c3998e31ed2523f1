"""The browser previewer: `sssjax preview SCENE`, built on viser.

A viser server (bound to 127.0.0.1 by default; its wheel ships the web client, so it works
offline) shows a rasterised version of the scene, which the user orbits, pans and zooms in
real time:

- every shape tessellated by `Shape.tessellate` of `sssjax.shapes` (the same definitions the
  tracer intersects), coloured by its material: diffuse albedo; translucent media tinted by
  their total diffuse reflectance `Rd_total` of the scene's `[sss] profile` per channel; mirrors as polished metal
  (a glTF material with metalness 1, reflecting viser's environment map);
- area lights as emissive parallelograms, point and beam lights as markers;
- the scene camera as a frustum (and the chosen render camera as a second, orange one).

The GUI panel holds "Use this view" (the browser's camera becomes the render camera, with
its field of view and aspect ratio), the render settings (height in pixels, spp, light
samples, SSS on/off, the transport: diffusion or volumetric), "Render" (progressive passes
with a progress bar; the image appears in the panel and on the render camera's image plane
in 3D), "Save" (image and a scene file with the chosen camera, never overwriting a file),
the surfaces' opacity, and the ray tree of one pixel (picked by x/y fields or by clicking
the rendered image in 3D), drawn as segments coloured by kind with a toggle per kind.

Everything the buttons do is a method of `Previewer`, so it runs without a browser.
"""

from __future__ import annotations

import dataclasses
import io
import math
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .raytree import COLORS as _RT_COLORS
from .scene import Camera, Scene, dump_scene, load_scene
from .transport import TRANSPORTS

__all__ = [
    "Previewer",
    "PreviewMesh",
    "POINT_COLOR",
    "RAY_COLORS",
    "camera_from_view",
    "camera_wxyz",
    "material_color",
    "merge_trees",
    "save_paths",
    "scene_meshes",
    "scene_toml",
]

# Ray-tree kinds (the order of `RayTree.KINDS`) and their colours (sRGB 0-255), the same as
# in the pictures of `sssjax raytree`.
RAY_COLORS: dict[str, tuple[int, int, int]] = {
    k: (int(h[1:3], 16), int(h[3:5], 16), int(h[5:7], 16)) for k, h in _RT_COLORS.items()
}
POINT_COLOR = (0, 229, 255)  # dipole sample points
POINT_MIN_WEIGHT = 0.01  # points lighter than this fraction of the heaviest are not drawn
_RAY_LABELS = {
    "camera": "camera rays",
    "reflected": "mirror reflections",
    "shadow": "shadow rays (lit)",
    "shadow_blocked": "shadow rays (blocked)",
    "ss_refracted": "single scattering: refracted path",
    "ss_light": "single scattering: light connection",
    "dipole": "dipole sample rays",
    "walk": "volumetric walk (inside)",
    "exit": "walk leaving the object",
    "bounce": "path continuing outside",
    "connection": "next-event connection",
}
_LIGHT_RGB = (255, 244, 214)  # display colour of emitters
_SCENE_CAMERA_RGB = (40, 40, 40)
_RENDER_CAMERA_RGB = (255, 140, 0)


# --- pure helpers (no server) -----------------------------------------------------------
@dataclass(frozen=True)
class PreviewMesh:
    """One surface of the preview: a world-space triangle mesh and how to draw it.

    `color` is linear RGB in [0, 1]; `style` is `"matte"` (diffuse and translucent
    materials), `"mirror"` or `"emitter"` (area lights).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    color: np.ndarray
    style: str


def material_color(material, profile: str = "dipole") -> np.ndarray:
    """The linear-RGB display colour of a `Material`.

    Diffuse: its albedo. Translucent: the medium's total diffuse reflectance
    `profiles.Rd_total(sigma_a, sigmap_s, eta, profile)` per channel (what a large slab of it
    reflects under uniform light; `profile` the scene's `[sss] profile`). Mirror: its
    reflectance.
    """
    if material.type == "diffuse":
        return np.clip(np.asarray(material.albedo, dtype=np.float64), 0.0, 1.0)
    if material.type == "mirror":
        return np.clip(np.asarray(material.reflectance, dtype=np.float64), 0.0, 1.0)
    from .profiles import Rd_total

    m = material.medium
    rd = Rd_total(m.sigma_a, m.sigmap_s, m.eta, profile)
    return np.clip(np.asarray(rd, dtype=np.float64), 0.0, 1.0)


def _to_rgb8(linear) -> tuple[int, int, int]:
    """A linear colour as viser wants it: 0-255 integers of the *linear* value (viser passes
    mesh colours to three.js, which treats them as linear and sRGB-encodes its output)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return tuple(int(v) for v in np.rint(c * 255.0))


def scene_meshes(scene: Scene, resolution: int = 48) -> list[PreviewMesh]:
    """The surfaces of the preview: every shape (tessellated) and every area light.

    Names: `/shapes/{i}_{kind}_{material}` and `/lights/{i}_area`.
    """
    out = []
    for i, spec in enumerate(scene.shapes):
        v, f = spec.shape.tessellate(resolution)
        mat = scene.materials[spec.material]
        style = "mirror" if mat.type == "mirror" else "matte"
        name = f"/shapes/{i}_{spec.kind}_{spec.material}"
        out.append(PreviewMesh(name, v, f, material_color(mat, scene.sss.profile), style))
    for i, light in enumerate(scene.lights):
        if type(light).__name__ != "AreaLight":
            continue
        c, u, w = (
            np.asarray(a, dtype=np.float64) for a in (light.corner, light.edge_u, light.edge_v)
        )
        v = np.stack([c, c + u, c + u + w, c + w])
        f = np.array([[0, 1, 2], [0, 2, 3]])  # counter-clockwise around u x v: the lit side
        out.append(PreviewMesh(f"/lights/{i}_area", v, f, np.ones(3), "emitter"))
    return out


def _scene_extent(scene: Scene) -> float:
    """A length scale of the scene (mm) for marker sizes: the scene camera's distance to its
    target (what the scene's author framed), at least the smallest shape's size."""
    cam = scene.camera
    dist = float(np.linalg.norm(np.asarray(cam.target) - np.asarray(cam.origin)))
    sizes = [float(np.linalg.norm(np.subtract(*s.shape.bounds()[::-1]))) for s in scene.shapes]
    return max(dist, min(sizes, default=dist))


def camera_wxyz(cam: Camera) -> np.ndarray:
    """The viser (OpenCV: x right, y down, z forward) orientation quaternion of a camera."""
    from viser import transforms as vtf

    fwd, right, up = cam.basis()
    R = np.stack([right, -up, fwd], axis=1)
    return np.asarray(vtf.SO3.from_matrix(R).wxyz)


def camera_from_view(
    position,
    look_at,
    up,
    fov: float,
    aspect: float,
    height: int,
    base: Camera | None = None,
) -> Camera:
    """A pinhole `Camera` from a browser view.

    **Arguments:**

    - `position`, `look_at`, `up`: world-space (mm) eye, orbit centre and up direction.
    - `fov`: vertical field of view in **radians** (viser's convention).
    - `aspect`: width / height of the view.
    - `height`: image height in pixels; the width is `round(height * aspect)`.
    - `base`: a camera whose other fields (e.g. `projection`) are kept, switched to pinhole.

    **Returns:** the `Camera` (fov in degrees).
    """
    o = np.asarray(position, dtype=np.float64)
    t = np.asarray(look_at, dtype=np.float64)
    u = np.asarray(up, dtype=np.float64)
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(t)) and np.all(np.isfinite(u))):
        raise ValueError("the view has a non-finite position, look-at point or up direction")
    fwd = t - o
    if np.linalg.norm(fwd) == 0:
        raise ValueError("the view's look-at point equals its position")
    if np.linalg.norm(np.cross(fwd / np.linalg.norm(fwd), u)) < 1e-6:
        raise ValueError("the view's up direction is parallel to its viewing direction")
    fov_deg = math.degrees(float(fov))
    if not 0 < fov_deg < 180:
        raise ValueError(f"the view's field of view must be in (0, 180) degrees, got {fov_deg:g}")
    height = int(height)
    if height < 1 or not aspect > 0:
        raise ValueError(f"bad image size: height {height}, aspect {aspect}")
    width = max(1, int(round(height * float(aspect))))
    kw: dict[str, Any] = dict(origin=o, target=t, up=u, fov=fov_deg, width=width, height=height)
    if base is not None:
        fields = {f.name for f in dataclasses.fields(base)}
        if "projection" in fields:
            kw["projection"] = "pinhole"
        return dataclasses.replace(base, **kw)
    return Camera(**kw)


def scene_toml(scene: Scene, camera: Camera, **render: Any) -> str:
    """The scene file of `scene` with `camera` as its camera and some `[render]` / `[sss]`
    fields replaced (`spp=`, `light_samples=`, `seed=`, `sss_enabled=`, `sss_transport=`).

    Written by `dump_scene`: quad meshes read from OBJ files by their absolute paths, so the
    file loads from any folder.
    """
    out = scene.replace(camera=camera).with_settings(**render)
    where = scene.path or "a scene dict"
    return dump_scene(out, header=f"written by `sssjax preview` from {where}; units: mm, 1/mm")


def save_paths(base: str | Path, protect=()) -> dict[str, Path]:
    """Free output names for a save: `{stem}.png`, `.exr`, `.toml` next to `base`.

    If any of them exists (or is a protected input), `_1`, `_2`, ... is appended to the stem
    until none does: a save never overwrites a file.
    """
    from ._files import free_stem

    base = Path(base)
    if base.suffix.lower() in (".png", ".exr", ".toml", ".jpg", ".tif"):
        base = base.with_suffix("")
    return free_stem(base, (".png", ".exr", ".toml"), protect)


# --- the server -------------------------------------------------------------------------
# `Previewer` is over 400 lines on purpose: it is one GUI object whose public methods are its
# buttons (`use_view`, `render`, `save`, `show_raytree`, `set_opacity`, each tested without a
# browser) over one shared state of scene nodes and controls; split, that state would be
# passed between classes that are only ever used together.
class Previewer:
    """The interactive previewer of one scene.

    ```python
    p = Previewer("scenes/marble_cube.toml", port=0).start()
    print(p.url)
    p.use_view(client.camera)  # or any object with position, look_at, up_direction, fov, aspect
    image = p.render()         # with the GUI's spp, light samples, SSS switch, transport
    p.save("out/view")         # out/view.png, .exr, .toml (or out/view_1.*, ...)
    p.stop()
    ```

    **Arguments:**

    - `scene`: a `Scene` or the path of a scene file.
    - `host`, `port`: where the server listens (port 0: any free port; a busy port is
      skipped upwards, as viser does).
    - `resolution`: tessellation segments around curved surfaces.
    - `output`: the default output path stem of "Save" (default `out/<scene>_view`).
    """

    def __init__(
        self,
        scene: Scene | str | Path,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        resolution: int = 48,
        output: str | Path | None = None,
    ):
        self.scene = scene if isinstance(scene, Scene) else load_scene(scene)
        self.host, self.port, self.resolution = host, int(port), int(resolution)
        stem = Path(self.scene.path).stem if self.scene.path else "scene"
        self.output = Path(output) if output is not None else Path("out") / f"{stem}_view"
        self.camera: Camera = self.scene.camera  # the render camera
        self.image: np.ndarray | None = None  # the last render (linear RGB)
        self.image_meta: dict = {}
        self.tree = None  # the last ray tree
        self.server = None
        self.nodes: dict[str, Any] = {}  # scene-node handles by name
        self.controls: dict[str, Any] = {}  # GUI handles by name
        self.meshes = scene_meshes(self.scene, self.resolution)
        self.extent = _scene_extent(self.scene)
        self._lock = threading.Lock()
        self._render_cache: tuple | None = None
        self._rendered: tuple | None = None  # (scene, camera) of the image
        self._opacity = 1.0

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> Previewer:
        """Start the server and build the scene and the GUI. Returns `self`."""
        import viser

        if self.server is not None:
            return self
        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
        self.port = self.server.get_port()
        self._build_scene()
        self._build_gui()
        return self

    def stop(self) -> None:
        """Stop the server (idempotent)."""
        if self.server is not None:
            self.server.stop()
            self.server = None

    def __enter__(self) -> Previewer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def url(self) -> str:
        """The address to open in a browser."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}/"

    # -- scene ---------------------------------------------------------------------------
    def _build_scene(self) -> None:
        sc = self.server.scene
        cam = self.scene.camera
        up = np.asarray(cam.basis()[2])
        sc.set_up_direction(tuple(float(x) for x in cam.up))
        ic = self.server.initial_camera
        # start a step behind the scene camera, so that its frustum is in view
        _, right, _ = cam.basis()
        dist = float(np.linalg.norm(cam.origin - cam.target))
        eye = cam.target + 1.5 * (cam.origin - cam.target) + dist * (0.5 * right + 0.3 * up)
        ic.position = tuple(float(x) for x in eye)
        ic.look_at = tuple(float(x) for x in cam.target)
        ic.up = tuple(float(x) for x in up)
        ic.fov = (
            math.radians(float(cam.fov))
            if getattr(cam, "projection", "pinhole") == "pinhole"
            else ic.fov
        )
        ic.near = max(1e-3, 0.002 * self.extent)
        ic.far = 200.0 * self.extent
        sc.configure_default_lights(enabled=False)
        sc.configure_environment_map("studio", environment_intensity=0.45)
        for m in self.meshes:
            self._add_mesh(m)
        r = 0.01 * self.extent
        for i, light in enumerate(self.scene.lights):
            kind = type(light).__name__
            if kind == "PointLight":
                self.nodes[f"/lights/{i}_point"] = sc.add_icosphere(
                    f"/lights/{i}_point", radius=r, color=_LIGHT_RGB, position=tuple(light.position)
                )
            elif kind == "BeamLight":
                p = np.asarray(light.position, dtype=np.float64)
                d = np.asarray(light.direction, dtype=np.float64)
                seg = np.stack([p, p + d * 0.5 * self.extent])[None]
                self.nodes[f"/lights/{i}_beam"] = sc.add_line_segments(
                    f"/lights/{i}_beam", seg, _LIGHT_RGB, thickness=4.0, thickness_units="screen"
                )
        self._add_camera("/camera/scene", cam, _SCENE_CAMERA_RGB)

    def _add_mesh(self, m: PreviewMesh) -> None:
        sc = self.server.scene
        if m.style == "matte":
            opacity = None if self._opacity >= 1.0 else self._opacity
            self.nodes[m.name] = sc.add_mesh_simple(
                m.name,
                m.vertices,
                m.faces,
                color=_to_rgb8(m.color),
                opacity=opacity,
                side="double",
            )
        else:
            self.nodes[m.name] = sc.add_glb(m.name, self._glb(m), cast_shadow=m.style != "emitter")

    def _glb(self, m: PreviewMesh) -> bytes:
        """A glTF binary of a mirror (metalness 1, roughness 0.05) or an emitter (emissive)."""
        import trimesh
        from trimesh.visual.material import PBRMaterial

        alpha = 1.0 if m.style == "emitter" else self._opacity
        if m.style == "mirror":
            mat = PBRMaterial(
                baseColorFactor=[*np.clip(m.color, 0, 1), alpha],
                metallicFactor=1.0,
                roughnessFactor=0.05,
                alphaMode="BLEND" if alpha < 1 else "OPAQUE",
                doubleSided=True,
            )
        else:
            mat = PBRMaterial(
                baseColorFactor=[1.0, 1.0, 1.0, 1.0],
                emissiveFactor=[c / 255 for c in _LIGHT_RGB],
                metallicFactor=0.0,
                roughnessFactor=1.0,
                doubleSided=False,
            )
        mesh = trimesh.Trimesh(m.vertices, m.faces, process=False)
        mesh.visual = trimesh.visual.TextureVisuals(material=mat)
        buf = io.BytesIO()
        mesh.export(buf, file_type="glb")
        return buf.getvalue()

    def _frustum_scale(self, cam: Camera) -> float:
        return 0.06 * self.extent

    def _add_camera(self, name: str, cam: Camera, rgb) -> None:
        sc = self.server.scene
        wxyz = camera_wxyz(cam)
        if getattr(cam, "projection", "pinhole") == "orthographic":
            fwd, right, up = cam.basis()
            hw = 0.5 * cam.view_width
            hh = hw * cam.height / cam.width
            o = np.asarray(cam.origin, dtype=np.float64)
            depth = self._frustum_scale(cam) * 2
            corners = [
                o + sx * hw * right + sy * hh * up
                for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))
            ]
            segs = []
            for k in range(4):
                a, b = corners[k], corners[(k + 1) % 4]
                segs += [(a, b), (a + depth * fwd, b + depth * fwd), (a, a + depth * fwd)]
            self.nodes[name] = sc.add_line_segments(
                name, np.asarray(segs), rgb, thickness=2.0, thickness_units="screen"
            )
            return
        self.nodes[name] = sc.add_camera_frustum(
            name,
            fov=math.radians(float(cam.fov)),
            aspect=cam.width / cam.height,
            scale=self._frustum_scale(cam),
            thickness=2.0,
            thickness_units="screen",
            color=rgb,
            wxyz=wxyz,
            position=tuple(float(x) for x in cam.origin),
        )

    def set_opacity(self, opacity: float) -> None:
        """Set the opacity of every shape's surface (0: invisible, 1: opaque)."""
        opacity = float(np.clip(opacity, 0.0, 1.0))
        self._opacity = opacity
        for m in self.meshes:
            if m.style == "matte":
                self.nodes[m.name].opacity = None if opacity >= 1.0 else opacity
            elif m.style == "mirror":
                self._add_mesh(m)  # re-sent with the new alpha

    # -- GUI -----------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        c = self.controls
        gui.configure_theme(control_width="medium", show_share_button=False, dark_mode=True)
        with gui.add_folder("Render"):
            c["use_view"] = gui.add_button(
                "Use this view", hint="the browser's view becomes the render camera"
            )
            c["height"] = gui.add_number("Height (px)", self.camera.height, min=1, max=4096, step=1)
            c["spp"] = gui.add_number("spp", self.scene.render.spp, min=1, max=4096, step=1)
            c["light_samples"] = gui.add_number(
                "Light samples", self.scene.render.light_samples, min=1, max=256, step=1
            )
            c["sss"] = gui.add_checkbox("SSS", self.scene.sss.enabled)
            c["transport"] = gui.add_dropdown(
                "Transport",
                TRANSPORTS.names,
                initial_value=self.scene.sss.transport,
                hint="diffusion: the dipole family, fast; volumetric: exact random walks",
            )
            c["render"] = gui.add_button("Render")
            c["progress"] = gui.add_progress_bar(0.0)
            c["status"] = gui.add_markdown(self._camera_text())
            c["output"] = gui.add_text("Save as", str(self.output))
            c["save"] = gui.add_button("Save", disabled=True)
            c["show_image"] = gui.add_checkbox("Image in 3D", True)
        with gui.add_folder("Display"):
            c["opacity"] = gui.add_slider("Opacity", 0.0, 1.0, 0.05, 1.0)
        with gui.add_folder("Ray tree"):
            c["px"] = gui.add_number("Pixel x", self.camera.width // 2, min=0, step=1)
            c["py"] = gui.add_number("Pixel y", self.camera.height // 2, min=0, step=1)
            c["trace"] = gui.add_button("Trace pixel", hint="or click the rendered image in 3D")
            for kind in RAY_COLORS:
                c[f"show_{kind}"] = gui.add_checkbox(_RAY_LABELS[kind], True)
            c["legend"] = gui.add_html(self._legend())
        self.image_handle = None

        c["use_view"].on_click(lambda e: self._guarded(lambda: self.use_view(e.client.camera)))
        c["render"].on_click(lambda e: self._guarded(self.render))
        c["save"].on_click(lambda e: self._guarded(self.save))
        c["opacity"].on_update(lambda e: self.set_opacity(c["opacity"].value))
        c["trace"].on_click(
            lambda e: self._guarded(
                lambda: self.show_raytree((int(c["px"].value), int(c["py"].value)))
            )
        )
        c["show_image"].on_update(lambda e: self._show_image_3d())
        for kind in RAY_COLORS:
            c[f"show_{kind}"].on_update(lambda e, k=kind: self._toggle_kind(k))

    def _legend(self, counts: dict | None = None) -> str:
        """The ray-tree legend: an HTML table of colour swatches, kinds and counts."""

        def row(rgb, label, n):
            sw = (
                "display:inline-block;width:1.6em;height:0.7em;border:1px solid #888;"
                "background:#{:02x}{:02x}{:02x}".format(*rgb)
            )
            return f'<tr><td><span style="{sw}"></span></td><td>{label}</td><td>{n}</td></tr>'

        get = (lambda k: "") if counts is None else (lambda k: str(counts.get(k, 0)))
        rows = [row(rgb, _RAY_LABELS[k], get(k)) for k, rgb in RAY_COLORS.items()]
        rows.append(row(POINT_COLOR, "dipole sample points (>= 1% of max weight)", get("points")))
        return '<table style="font-size:0.8em;width:100%">' + "".join(rows) + "</table>"

    def _camera_text(self, extra: str = "") -> str:
        cam = self.camera
        o = ", ".join(f"{x:.1f}" for x in cam.origin)
        t = ", ".join(f"{x:.1f}" for x in cam.target)
        text = f"camera ({o}) -> ({t}), fov {cam.fov:.1f} deg, {cam.width}x{cam.height} px"
        return text + (f"  \n{extra}" if extra else "")

    def _status(self, extra: str) -> None:
        if "status" in self.controls:
            self.controls["status"].content = self._camera_text(extra)

    def _guarded(self, fn) -> None:
        """Run a GUI action, showing an error in the status line instead of a traceback."""
        try:
            fn()
        except Exception as e:  # noqa: BLE001 - shown to the user
            print(f"sssjax preview: error: {e}", file=sys.stderr, flush=True)
            self._status(f"**error:** {e}")

    # -- actions -------------------------------------------------------------------------
    def use_view(self, view, height: int | None = None) -> Camera:
        """Take a browser view as the render camera.

        **Arguments:**

        - `view`: viser's `client.camera` (or any object with `position`, `look_at`,
          `up_direction`, `fov` in radians and `aspect`).
        - `height`: image height in pixels (default: the GUI's "Height" field).

        **Returns:** the new render `Camera`.
        """
        if height is not None and "height" in self.controls:
            self.controls["height"].value = int(height)
        if height is None:
            height = (
                int(self.controls["height"].value)
                if "height" in self.controls
                else self.camera.height
            )
        self.camera = camera_from_view(
            view.position,
            view.look_at,
            view.up_direction,
            view.fov,
            view.aspect,
            height,
            base=self.camera,
        )
        if self.server is not None:
            self._add_camera("/camera/render", self.camera, _RENDER_CAMERA_RGB)
            self.controls["px"].value = self.camera.width // 2
            self.controls["py"].value = self.camera.height // 2
            old = self.nodes.pop("/render_image", None)  # it belongs to the previous camera
            if old is not None:
                old.remove()
            self._status("view taken; press Render")
        return self.camera

    def render_scene(self) -> Scene:
        """The scene that "Render" traces: the chosen camera and the GUI's settings.

        The same object is returned while nothing changed, so its compiled renderer is reused.
        """
        c = self.controls
        spp = int(c["spp"].value) if "spp" in c else self.scene.render.spp
        ls = (
            int(c["light_samples"].value)
            if "light_samples" in c
            else self.scene.render.light_samples
        )
        sss = bool(c["sss"].value) if "sss" in c else self.scene.sss.enabled
        transport = str(c["transport"].value) if "transport" in c else self.scene.sss.transport
        if spp < 1 or ls < 1:
            raise ValueError(f"spp and light samples must be >= 1, got {spp} and {ls}")
        key = (spp, ls, sss, transport)
        hit = self._render_cache is not None and self._render_cache[0] == key
        if not hit or self._render_cache[3] is not self.camera:
            per_pass = max(d for d in (1, 2, 4) if spp % d == 0)
            sc = self.scene.replace(camera=self.camera).with_settings(
                spp=per_pass, light_samples=ls, sss_enabled=sss, sss_transport=transport
            )
            self._render_cache = (key, sc, spp // per_pass, self.camera)
        return self._render_cache[1]

    def render(self) -> np.ndarray:
        """Ray trace the render scene with `sssjax.render`, in passes of up to 4 spp each.

        After every pass the progress bar, the status line and the shown image are updated
        (the running mean of the passes; pass `i` uses seed `scene seed + i`).

        **Returns:** the `(height, width, 3)` linear-RGB image.
        """
        from .imageio import render_metadata
        from .render import render

        if not self._lock.acquire(blocking=False):
            raise RuntimeError("a render is already running")
        try:
            scene = self.render_scene()
            n_pass = self._render_cache[2]
            spp = scene.render.spp * n_pass
            self._set_busy(True)
            t0 = time.perf_counter()
            acc = None
            seeds = []
            for i in range(n_pass):
                seed = scene.render.seed + i
                self._status(
                    f"rendering pass {i + 1}/{n_pass}, {time.perf_counter() - t0:.0f} s"
                    + (" (new settings compile first)" if i == 0 else "")
                )
                img = np.asarray(render(scene, seed), dtype=np.float64)
                acc = img if acc is None else acc + img
                seeds.append(seed)
                self.image = (acc / (i + 1)).astype(np.float32)
                self._progress(100.0 * (i + 1) / n_pass)
                self._show_image()
            dt = time.perf_counter() - t0
            cam = scene.camera
            self._rendered = (scene, self.camera)
            self.image_meta = render_metadata(scene, spp=spp, seeds=seeds)
            self._status(f"rendered {cam.width}x{cam.height} at {spp} spp in {dt:.1f} s")
            return self.image
        finally:
            self._set_busy(False)
            self._lock.release()

    def _set_busy(self, busy: bool) -> None:
        c = self.controls
        if "render" in c:
            c["render"].disabled = busy
            c["use_view"].disabled = busy
            c["save"].disabled = busy or self.image is None
            c["progress"].animated = busy
            if busy:
                c["progress"].value = 0.0

    def _progress(self, pct: float) -> None:
        if "progress" in self.controls:
            self.controls["progress"].value = float(np.clip(pct, 0.0, 100.0))

    def _display_image(self) -> np.ndarray:
        from .imageio import srgb_encode

        s = srgb_encode(np.clip(self.image, 0.0, 1.0))
        return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)

    def _show_image(self) -> None:
        if self.server is None or self.image is None:
            return
        img8 = self._display_image()
        if self.image_handle is None:
            with self.server.gui.add_folder("Rendered image"):
                self.image_handle = self.server.gui.add_image(img8, format="png")
        else:
            self.image_handle.image = img8
        self._show_image_3d()

    def image_plane(self) -> tuple[np.ndarray, float]:
        """Where the rendered image is drawn in 3D: `(centre, distance)`, on the render
        camera's image plane at `distance` mm in front of its origin."""
        cam = self.camera
        # the depth of the rectangle of viser's frustum (its client scales the frustum to a
        # fixed volume): the image fills it
        y = math.tan(math.radians(cam.fov) / 2)
        d = self._frustum_scale(cam) / np.cbrt(y * y * (cam.width / cam.height) / 3.0)
        fwd = cam.basis()[0]
        return np.asarray(cam.origin) + d * fwd, d

    def _show_image_3d(self) -> None:
        if self.server is None:
            return
        old = self.nodes.pop("/render_image", None)
        if old is not None:
            old.remove()
        if self.image is None or not self.controls["show_image"].value:
            return
        cam = self.camera
        if getattr(cam, "projection", "pinhole") != "pinhole":
            return
        centre, d = self.image_plane()
        h = 2.0 * d * math.tan(math.radians(cam.fov) / 2)
        w = h * cam.width / cam.height
        handle = self.server.scene.add_image(
            "/render_image",
            self._display_image(),
            render_width=w,
            render_height=h,
            format="png",
            wxyz=camera_wxyz(cam),
            position=tuple(float(x) for x in centre),
            cast_shadow=False,
            receive_shadow=False,
        )
        handle.on_click(lambda e: self._guarded(lambda: self._pick(e.ray_origin, e.ray_direction)))
        self.nodes["/render_image"] = handle

    def pixel_at(self, ray_origin, ray_direction) -> tuple[int, int] | None:
        """The pixel of the rendered image that a ray (e.g. a click in the browser) hits on
        the image plane drawn in 3D, or `None` when it misses the image."""
        cam = self.camera
        centre, _ = self.image_plane()
        fwd = np.asarray(cam.basis()[0])
        o = np.asarray(ray_origin, dtype=np.float64)
        dvec = np.asarray(ray_direction, dtype=np.float64)
        den = float(dvec @ fwd)
        if abs(den) < 1e-12:
            return None
        t = float((centre - o) @ fwd) / den
        if t <= 0:
            return None
        from .camera import project

        xy = np.asarray(project(cam, (o + t * dvec)[None]))[0]
        x, y = int(math.floor(xy[0])), int(math.floor(xy[1]))
        if 0 <= x < cam.width and 0 <= y < cam.height:
            return x, y
        return None

    def _pick(self, ray_origin, ray_direction) -> None:
        px = self.pixel_at(ray_origin, ray_direction)
        if px is None:
            return
        self.controls["px"].value, self.controls["py"].value = px
        self.show_raytree(px)

    def save(self, path: str | Path | None = None) -> dict[str, Path]:
        """Write the last render and a scene file with its camera.

        **Arguments:** `path`: output stem (default: the GUI's "Save as" field); `.png`
        (sRGB), `.exr` (linear) and `.toml` are written next to each other. When any of them
        exists, a free stem `_1`, `_2`, ... is chosen: nothing is ever overwritten, the
        original scene file included.

        **Returns:** the paths written, by extension.
        """
        from ._files import write_text
        from .imageio import write_image

        if self.image is None:
            raise ValueError("nothing to save: press Render first")
        if path is None:
            path = self.controls["output"].value if "output" in self.controls else self.output
        protect = [self.scene.path] if self.scene.path else []
        paths = save_paths(path, protect)
        scene, camera = self._rendered  # what the image shows, whatever changed since
        meta = self.image_meta
        text = scene_toml(
            self.scene,
            camera,
            spp=int(self.image_meta.get("spp", scene.render.spp)),
            light_samples=int(scene.render.light_samples),
            sss_enabled=bool(scene.sss.enabled),
            sss_transport=scene.sss.transport,
        )
        # atomic, and failing rather than replacing a file that appeared meanwhile
        write_text(paths["toml"], text, overwrite=False)
        for ext in ("png", "exr"):
            write_image(
                paths[ext], self.image, metadata=meta, overwrite_protect=protect, overwrite=False
            )
        self._status("saved " + ", ".join(str(p) for p in paths.values()))
        return paths

    # -- ray tree ------------------------------------------------------------------------
    def show_raytree(self, pixel: tuple[int, int]):
        """Record the rays behind one pixel of the current render settings and draw them.

        The rays are those of "Render": `sssjax.raytree` of every render pass (seed
        `scene seed + i`) merged into one tree, sample indices numbered across passes.
        Segments are drawn coloured by kind, dipole sample points sized by weight.

        **Returns:** the merged `RayTree`.
        """
        from .raytree import raytree

        x, y = int(pixel[0]), int(pixel[1])
        cam = self.camera
        if not (0 <= x < cam.width and 0 <= y < cam.height):
            raise ValueError(f"pixel ({x}, {y}) is outside the {cam.width}x{cam.height} image")
        if "px" in self.controls:
            self.controls["px"].value, self.controls["py"].value = x, y
        scene = self.render_scene()
        n_pass = self._render_cache[2]
        trees = []
        for i in range(n_pass):
            self._status(f"tracing the rays of pixel ({x}, {y}), pass {i + 1}/{n_pass}")
            trees.append(raytree(scene, pixel=(x, y), key=scene.render.seed + i))
        tree = merge_trees(trees)
        self.tree = tree
        self.draw_raytree(tree)
        self._status(f"ray tree of pixel ({x}, {y}): {len(tree.kind)} rays")
        return tree

    def draw_raytree(self, tree) -> None:
        """Draw a `RayTree` (replacing the previous one): a line-segment node per kind,
        `/raytree/KIND`, and dipole sample points in four size classes by weight,
        `/raytree/dipole/points{0..3}`; the legend shows the counts."""
        for name in [n for n in self.nodes if n.startswith("/raytree/")]:
            self.nodes.pop(name).remove()
        kind = np.asarray(tree.kind)
        origin = np.asarray(tree.origin, dtype=np.float64).reshape(-1, 3)
        end = np.asarray(tree.end, dtype=np.float64).reshape(-1, 3)
        counts = {name: int(np.sum(kind == code)) for code, name in enumerate(tree.KINDS)}
        sc = self.server.scene if self.server is not None else None

        def shown(name: str) -> bool:
            h = self.controls.get(f"show_{name}")
            return True if h is None else bool(h.value)

        for code, name in enumerate(tree.KINDS):
            sel = kind == code
            if not sel.any() or sc is None:
                continue
            node = f"/raytree/{name}"
            self.nodes[node] = sc.add_line_segments(
                node,
                np.stack([origin[sel], end[sel]], axis=1),
                RAY_COLORS.get(name, (200, 200, 200)),
                thickness=2.0,
                thickness_units="screen",
                visible=shown(name),
            )
        pts = np.asarray(tree.points, dtype=np.float64).reshape(-1, 3)
        w = np.asarray(tree.point_weight, dtype=np.float64).reshape(-1)
        n_all = int(np.sum(w > 0))  # points replaced by the near-field term have weight 0
        keep = w >= POINT_MIN_WEIGHT * (w.max() if len(w) else 0.0)
        keep &= w > 0
        pts, w = pts[keep], w[keep]
        counts["points"] = f"{len(pts)} of {n_all}" if len(pts) < n_all else str(n_all)
        if len(pts) and sc is not None:
            # a point cloud has one point size: four classes by weight (area ~ weight)
            size_class = np.minimum((np.sqrt(w / w.max()) * 4).astype(int), 3)
            for b in range(4):
                sel = size_class == b
                if sel.any():
                    node = f"/raytree/dipole/points{b}"
                    self.nodes[node] = sc.add_point_cloud(
                        node,
                        pts[sel].astype(np.float32),
                        POINT_COLOR,
                        point_size=0.001 * self.extent * (b + 1),
                        point_shape="circle",
                        precision="float32",
                        visible=shown("dipole"),
                    )
        if "legend" in self.controls:
            self.controls["legend"].content = self._legend(counts)

    def _toggle_kind(self, kind: str) -> None:
        show = bool(self.controls[f"show_{kind}"].value)
        for name, h in self.nodes.items():
            if name == f"/raytree/{kind}" or name.startswith(f"/raytree/{kind}/"):
                h.visible = show


def merge_trees(trees: list):
    """One `RayTree` from the trees of several render passes of the same pixel: segments and
    points concatenated, sample indices (and parents) renumbered, radiance averaged."""
    if len(trees) == 1:
        return trees[0]
    seg: dict[str, list] = {
        k: [] for k in ("origin", "end", "kind", "depth", "sample", "parent", "miss")
    }
    pts: dict[str, list] = {k: [] for k in ("points", "point_weight", "point_sample")}
    n_seg, n_smp = 0, 0
    for t in trees:
        for k in seg:
            v = np.asarray(getattr(t, k))
            if k == "sample":
                v = v + n_smp
            elif k == "parent":
                v = np.where(v >= 0, v + n_seg, v)
            seg[k].append(v)
        for k in pts:
            v = np.asarray(getattr(t, k))
            pts[k].append(v + n_smp if k == "point_sample" else v)
        n_seg += len(t.kind)
        n_smp += int(t.spp)
    fields = {k: np.concatenate(v) for k, v in {**seg, **pts}.items()}
    radiance = np.mean([np.asarray(t.radiance) for t in trees], axis=0)
    return dataclasses.replace(trees[0], spp=n_smp, radiance=radiance, **fields)


def serve(path: str | Path, *, host: str = "127.0.0.1", port: int = 8080) -> None:
    """Run the previewer of a scene file until Ctrl-C (the `sssjax preview` command)."""
    p = Previewer(path, host=host, port=port)
    try:
        p.start()
        print(f"sssjax preview: open {p.url} in a browser (Ctrl-C to stop)", flush=True)
        while True:
            time.sleep(0.5)  # short sleeps: Ctrl-C is seen promptly
    except KeyboardInterrupt:
        pass
    finally:
        # a server thread that does not wind down must not keep the process alive after
        # Ctrl-C: give stop() 10 s, then leave anyway
        import os
        import threading

        watchdog = threading.Timer(10.0, lambda: os._exit(0))
        watchdog.daemon = True
        watchdog.start()
        p.stop()
        watchdog.cancel()
