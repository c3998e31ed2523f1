"""The `sssjax` command line: `sssjax materials`, `sssjax demo`, ...

User mistakes (bad files, bad values) print one line `sssjax: error: ...` and exit with
status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np


class UserError(Exception):
    """An error caused by the user's input: reported in one line, without a traceback."""


def materials_table(profile: str = "dipole") -> str:
    """The measured presets with their derived quantities, as a fixed-width text table
    (total diffuse reflectance of the named `profile`)."""
    from .media import preset, preset_names
    from .profiles import Rd_total

    def trip(v, fmt):
        return " ".join(fmt.format(x) for x in np.asarray(v))

    head = (
        f"{'name':<10} {'sigmap_s [1/mm] R G B':<20} {'sigma_a [1/mm] R G B':<23} "
        f"{'total R_d  R G B':<19} {'1/sigma_tr [mm] R G B':<22}"
    )
    lines = [head, "-" * len(head)]
    for name in preset_names():
        m = preset(name)
        lines.append(
            f"{name:<10} {trip(m.sigmap_s, '{:5.2f}'):<20} {trip(m.sigma_a, '{:7.4f}'):<23} "
            f"{trip(Rd_total(m.sigma_a, m.sigmap_s, m.eta, profile), '{:5.3f}'):<19} "
            f"{trip(m.diffuse_mean_free_path, '{:6.2f}'):<22}"
        )
    names = {
        "dipole": "the classic dipole",
        "better_dipole": "the better dipole",
        "pbd": "PBD",
        "tabulated": "exact transport (tabulated)",
    }
    lines.append(
        f"(Jensen et al. 2001; g = 0, eta = 1.3; total R_d of {names.get(profile, profile)})"
    )
    return "\n".join(lines)


def _cmd_materials(args: argparse.Namespace) -> int:
    print(materials_table(args.profile))
    return 0


def render_to_files(
    scene,
    outputs: list[Path],
    *,
    seed: int | None,
    exposure: float,
    tonemap: str,
    quiet: bool = False,
) -> list[Path]:
    """Render `scene` with a progress bar and write every path in `outputs`."""
    import time

    from ._files import scene_inputs
    from .imageio import render_metadata, write_image
    from .render import render

    t0 = time.perf_counter()
    seed = scene.render.seed if seed is None else seed
    image = render(scene, seed, progress=not quiet)
    dt = time.perf_counter() - t0
    meta = render_metadata(scene, seed=seed)
    protect = scene_inputs(scene)
    written = []
    for out in outputs:
        written.append(
            write_image(
                out,
                image,
                metadata=meta,
                exposure=exposure,
                tonemap=tonemap,
                overwrite_protect=protect,
            )
        )
    if not quiet:
        cam = scene.camera
        print(f"rendered {cam.width}x{cam.height} at {scene.render.spp} spp in {dt:.1f} s")
    return written


def _check_image_outputs(scene, outputs: list[Path], exposure: float) -> None:
    """What `write_image` would refuse after the render, refused before it: unknown
    extensions, a non-finite exposure, too little memory or disk."""
    import math

    from ._budget import check_disk, check_memory
    from .imageio import DISPLAY_EXTENSIONS, FLOAT_EXTENSIONS

    known = FLOAT_EXTENSIONS + DISPLAY_EXTENSIONS
    for out in outputs:
        if out.suffix.lower() not in known:
            raise UserError(
                f"{out}: unknown image extension {out.suffix or '(none)'!r}; "
                f"expected one of {', '.join(known)}"
            )
    if not math.isfinite(exposure):
        raise UserError(f"--exposure must be finite, got {exposure:g}")
    png = any(o.suffix.lower() in DISPLAY_EXTENSIONS for o in outputs)
    check_memory(scene, png=png)
    check_disk(outputs, scene.camera.width, scene.camera.height)


def _cmd_render(args: argparse.Namespace) -> int:
    from ._files import check_outputs, scene_inputs
    from .scene import load_scene

    scene = load_scene(args.scene)
    kw = {}
    if args.spp is not None:
        kw["spp"] = args.spp
    if args.width is not None:
        kw["width"] = args.width
    if args.height is not None:
        kw["height"] = args.height
    if args.no_sss:
        kw["sss_enabled"] = False
    if args.transport is not None:
        kw["sss_transport"] = args.transport
    for k, v in kw.items():
        if k in ("spp", "width", "height") and v < 1:
            raise UserError(f"--{k} must be >= 1, got {v}")
    if args.seed is not None and args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    scene = scene.with_settings(**kw) if kw else scene
    stem = Path(args.scene).stem
    outputs = [Path(o) for o in args.output] or [
        Path("out") / f"{stem}.png",
        Path("out") / f"{stem}.exr",
    ]
    check_outputs(outputs, force=args.force, inputs=scene_inputs(scene))
    _check_image_outputs(scene, outputs, args.exposure)
    for path in render_to_files(
        scene, outputs, seed=args.seed, exposure=args.exposure, tonemap=args.tonemap
    ):
        print(f"wrote {path.resolve()}")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    from ._files import check_outputs, scene_inputs
    from .fit import FitError, fit, load_fit_file
    from .imageio import read_image, write_image
    from .plots import convergence_plot, fit_triptych
    from .render import render

    job = load_fit_file(args.fit_file)
    out = Path(args.output) if args.output else job.output
    if job.target is not None and out.resolve() == job.target.resolve().parent:
        raise UserError(f"refusing to write results into the target's folder {out}")
    names = ("result.json", "fit.exr", "fit.png", "triptych.png", "convergence.png")
    inputs = [Path(args.fit_file), *scene_inputs(job.scene)]
    inputs += [job.target] if job.target is not None else []
    check_outputs([out / n for n in names], force=args.force, inputs=inputs)
    scene = job.scene
    if job.target is None:
        sc = job.synthetic_scene or scene
        how = f"{sc.sss.transport} transport, {sc.render.spp} spp, seed {job.synthetic_seed}"
        print(f"rendering a synthetic target ({how}) from the scene's media")
        target = render(sc, job.synthetic_seed, progress=True)
    else:
        target = job.target  # `fit` reads it, naming the file in its errors
    try:
        res = fit(scene, target, **job.fit_kwargs(), progress=True)
    except FitError as e:  # what the fit file asked for: name it
        raise UserError(f"{job.path}: {e}") from None
    if job.target is not None:
        target = read_image(job.target)
    out.mkdir(parents=True, exist_ok=True)
    fitted = render(res.apply(scene), job.seed) * res.exposure
    write_image(out / "fit.exr", fitted)
    write_image(out / "fit.png", fitted)
    _, psnr, ssim = fit_triptych(np.asarray(target), fitted, out / "triptych.png", res.highlights)
    convergence_plot(res.history, res.names, out / "convergence.png", res.eta_search)
    res.to_json(out / "result.json")
    print(res.summary())
    print(
        f"PSNR {psnr:.2f} dB, SSIM {ssim:.4f} (fit vs target); wall {res.wall_time_s:.1f} s "
        f"(trace {res.trace_time_s:.1f} s)"
    )
    print(f"wrote {out.resolve()}/{{result.json, fit.exr, fit.png, triptych.png, convergence.png}}")
    return 0 if res.converged else 1


def _check_measure_flags(args: argparse.Namespace) -> None:
    """The measure command's numbers, checked before the image is read."""
    import math

    def finite(flag, v):
        if v is not None and not math.isfinite(v):
            raise UserError(f"{flag} must be finite, got {v:g}")

    for flag, v in (("--r-min", args.r_min), ("--r-max", args.r_max), ("--power", args.power)):
        finite(flag, v)
    for v in args.center or ():
        finite("--center", v)
    if args.r_min is not None and args.r_min < 0:
        raise UserError(f"--r-min must be >= 0 mm, got {args.r_min:g}")
    r_min = args.r_min or 0.0
    if args.r_max is not None and not args.r_max > r_min:
        raise UserError(f"--r-max must be > --r-min ({r_min:g} mm), got {args.r_max:g}")
    if args.power is not None and not args.power > 0:
        raise UserError(f"--power must be > 0 W, got {args.power:g}")
    for flag, v in (("--incidence", args.incidence), ("--view-angle", args.view_angle)):
        if not -90 < v < 90:
            raise UserError(f"{flag} must be between -90 and 90 degrees (exclusive), got {v:g}")


def _cmd_params(args: argparse.Namespace) -> int:
    from .params import parameters
    from .scene import load_scene

    print(f"{'parameter':<28} {'enters':<10} value (mm, 1/mm; lights and exposure: factors)")
    for p in parameters(load_scene(args.scene)).values():
        v = np.atleast_1d(np.asarray(p.value, dtype=np.float64))
        print(f"{p.name:<28} {p.enters.value:<10} {' '.join(f'{x:.6g}' for x in v)}")
    return 0


def _identifiability(prof, eta: float, r_min: float, orders: str) -> None:
    """Print the diffusion length `1 / sigma_tr` that a quick free-scale fit implies, per
    channel, against the profile's range, and warn where the range is shorter than two
    diffusion lengths: `sigma_a` then rests on the absolute level, not on the shape."""
    from .measure import fit_profile
    from .profiles import sigma_tr_better

    quick = fit_profile(
        prof,
        eta,
        r_min=r_min,
        free_scale=True,
        model="better_dipole",
        orders=orders,
        max_steps=60,
    )
    ell = 1.0 / np.asarray(sigma_tr_better(quick.sigma_a, quick.sigmap_s), np.float64)
    span = float(prof.r.max()) - r_min
    n = span / ell
    print(
        "diffusion length 1/sigma_tr (quick free fit): "
        + ", ".join(f"{'RGB'[c]} {ell[c]:.3g} mm" for c in range(3))
        + f"; the profile spans {span:.3g} mm = "
        + ", ".join(f"{n[c]:.2g}" for c in range(3))
        + " of them"
    )
    short = [c for c in range(3) if n[c] < 2.0]
    if short:
        chans = "/".join("RGB"[c] for c in short)
        warnings.warn(
            f"the profile spans fewer than two diffusion lengths in {chans}: sigma_a there "
            "rests on the absolute level (the beam power and calibration), not on the "
            "profile's shape; a larger image (or --r-max) or a known power helps",
            stacklevel=2,
        )


def _cmd_measure(args: argparse.Namespace) -> int:
    import json

    from ._files import check_outputs, write_text
    from ._tabulated import EtaRangeWarning
    from .imageio import read_image, read_metadata
    from .measure import find_center, fit_profile, image_to_reflectance, radial_profile
    from .plots import measurement_plot

    _check_measure_flags(args)
    path = Path(args.image)
    out = Path(args.output) if args.output else Path("out") / f"measure-{path.stem}"
    if out.resolve() == path.resolve().parent:
        raise UserError(f"refusing to write results into the image's folder {out}")
    check_outputs([out / "measure.json", out / "profile.png"], force=args.force, inputs=[path])
    image = read_image(path)
    meta = read_metadata(path)
    if not np.all(np.isfinite(image)):
        raise UserError(f"{path}: the image has NaN or infinite pixels")
    if not np.any(image > 0):
        raise UserError(f"{path}: the image is all black")
    if "transport" in meta and not meta.get("beams"):  # an sssjax render, and not of a beam
        raise UserError(
            f"{path}: rendered by sssjax with no beam light: sssjax measure fits the radial "
            'profile around a pencil beam on a flat sample ([[lights]] type = "beam")'
        )
    pixel = args.pixel_size if args.pixel_size is not None else meta.get("pixel_size_mm")
    if pixel is None:
        raise UserError(f"{path}: no pixel size in the image metadata: give --pixel-size MM")
    if pixel == float("inf"):
        raise UserError(f"--pixel-size must be finite, got {pixel:g}")
    if not pixel > 0:
        raise UserError(f"--pixel-size must be > 0 mm, got {pixel:g}")
    media = meta.get("media") or {}
    eta = args.eta
    if eta is None:
        etas = {m.get("eta") for m in media.values()} if isinstance(media, dict) else set()
        eta = etas.pop() if len(etas) == 1 else 1.3
    if eta == float("inf"):
        raise UserError(f"--eta must be finite, got {eta:g}")
    if not eta > 0:
        raise UserError(f"--eta must be > 0, got {eta:g}")
    power = args.power
    if power is None and not args.free_scale and len(meta.get("beams") or []) == 1:
        power = meta["beams"][0]["power"]
    free = args.free_scale or power is None
    h, w = image.shape[:2]
    center = tuple(args.center) if args.center else find_center(image)
    if not (0 <= center[0] <= w and 0 <= center[1] <= h):
        raise UserError(f"--center {center[0]:g} {center[1]:g} lies outside the {w}x{h} image")
    R = image_to_reflectance(
        image, eta, power, incidence_deg=args.incidence, view_deg=args.view_angle
    )
    prof = radial_profile(R, center, pixel, r_max_mm=args.r_max)
    # with single scattering in the model the centre is usable, except the first two
    # annuli, where the steep profile's annulus mean and its value at the mean radius differ
    # a photograph holds every order; sssjax's diffusion transport renders a beam's
    # multiple scattering only
    diffusion_render = meta.get("transport") == "diffusion" and bool(meta.get("beams"))
    rendered_ms = args.orders is None and diffusion_render
    orders = args.orders or ("multiple" if rendered_ms else "all")
    # exact transport for a photograph; a diffusion render is fitted with its own profile
    model = args.model or (meta.get("profile", "dipole") if diffusion_render else "tabulated")
    if model == "tabulated":
        from ._tabulated import eta_outside

        # said here, before the annuli are checked; `fit_profile`'s own warning is then muted
        if note := eta_outside(eta):
            warnings.warn(f"--eta {note}; --model better_dipole has no such limit", stacklevel=1)
    r_min = args.r_min
    if r_min is None:
        r_min = 2.0 * pixel if orders == "all" else 1.0
    n_used = int(np.sum(prof.r >= r_min))
    if n_used < 4:
        raise UserError(
            f"only {n_used} annuli beyond --r-min {r_min:g} mm (profile reaches "
            f"{prof.r.max():.3g} mm): lower --r-min or give a larger image"
        )
    print(
        f"{path}: {w}x{h} px, {pixel:.4g} mm/px, centre ({center[0]:.1f}, {center[1]:.1f}) px, "
        f"eta {eta:g}, r {r_min:g}..{prof.r.max():.1f} mm, model {model}, "
        f"orders {orders}"
        + (" (a diffusion-transport render: no single scattering), " if rendered_ms else ", ")
        + ("free intensity scale" if free else f"beam power {np.ravel(power).tolist()} W")
    )
    _identifiability(prof, eta, r_min, orders)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EtaRangeWarning)
        res = fit_profile(prof, eta, r_min=r_min, free_scale=free, model=model, orders=orders)
    print(f"{'ch':<3} {'sigma_a [1/mm]':>22} {'sigmap_s [1/mm]':>22} {'scale':>16}  steps")
    for c in range(3):
        sc = f"{res.scale[c]:.4g} +- {res.scale_stderr[c]:.2g}" if free else "1 (known)"
        print(
            f"{'RGB'[c]:<3} {res.sigma_a[c]:>11.5g} +- {res.sigma_a_stderr[c]:<8.2g} "
            f"{res.sigmap_s[c]:>11.5g} +- {res.sigmap_s_stderr[c]:<8.2g} {sc:>16}  "
            f"{res.steps[c]}{'' if res.converged[c] else ' (not converged)'}"
        )
    if free:
        print(
            "note: with a free scale sigma_a is set by the profile's shape alone; "
            "its error bar says how well"
        )
    out.mkdir(parents=True, exist_ok=True)
    plot = measurement_plot(prof, res, eta, out / "profile.png", r_min=r_min)
    result = {
        "image": str(path),
        "pixel_size_mm": pixel,
        "center_px": list(center),
        "eta": eta,
        "r_min_mm": r_min,
        "free_scale": free,
        "model": model,
        "orders": orders,
        "units": "coefficients 1/mm",
        **{
            k: np.asarray(getattr(res, k)).tolist()
            for k in (
                "sigma_a",
                "sigmap_s",
                "scale",
                "sigma_a_stderr",
                "sigmap_s_stderr",
                "scale_stderr",
            )
        },
        "steps": res.steps,
        "converged": res.converged,
    }
    write_text(out / "measure.json", json.dumps(result, indent=2))
    print(f"wrote {(out / 'measure.json').resolve()} and {plot.resolve()}")
    return 0 if all(res.converged) else 1


def _cmd_demo(args: argparse.Namespace) -> int:
    from ._files import check_outputs
    from .plots import plot_profiles
    from .scene import load_scene

    for flag, v in (("--size", args.size), ("--spp", args.spp)):
        if v < 0:
            raise UserError(f"{flag} must be >= 1 (or 0: the scene's), got {v}")
    out = Path(args.out)
    names = ("rd_profiles.png", "marble_cube.png", "marble_cube.exr")
    check_outputs([out / n for n in names], force=args.force)
    print(materials_table())
    path = plot_profiles(
        ["marble", "skimmilk", "ketchup", "skin1", "wholemilk", "apple"], out / "rd_profiles.png"
    )
    print(f"\nwrote the R_d(r) plot to {path.resolve()}")
    scene_path = Path(__file__).resolve().parent.parent / "scenes" / "marble_cube.toml"
    if not scene_path.exists():
        scene_path = Path("scenes/marble_cube.toml")
    scene = load_scene(scene_path)
    if args.size:
        scene = scene.with_settings(width=args.size, height=args.size)
    if args.spp:
        scene = scene.with_settings(spp=args.spp)
    outputs = [out / "marble_cube.png", out / "marble_cube.exr"]
    _check_image_outputs(scene, outputs, args.exposure)
    print(f"\nrendering {scene_path} (compiles first; about a minute on 2 cores) ...")
    for p in render_to_files(
        scene,
        outputs,
        seed=None,
        exposure=args.exposure,
        tonemap="clip",
    ):
        print(f"wrote {p.resolve()}")
    return 0


def _cmd_raytree(args: argparse.Namespace) -> int:
    from .raytree import raytree_files

    _, js, png = raytree_files(
        args.scene,
        tuple(args.pixel),
        json_path=args.output,
        png_path=args.png,
        seed=args.seed,
        image_path=args.image,
        force=args.force,
    )
    print(f"wrote {js.resolve()}\nwrote {png.resolve()}")
    return 0


def _cmd_preview(args: argparse.Namespace) -> int:
    from .viewer import serve

    if not 0 <= args.port <= 65535:
        raise UserError(f"--port must be in 0..65535, got {args.port}")
    serve(args.scene, host=args.host, port=args.port)
    return 0


_NO_CACHE_HELP = (
    "compile from scratch: do not read or write the compilation cache "
    "(default: SSSJAX_CACHE_DIR, else ~/.cache/sssjax/jax)"
)


def build_parser() -> argparse.ArgumentParser:
    from ._version import __version__
    from .profiles import PROFILES

    p = argparse.ArgumentParser(
        prog="sssjax",
        description="Differentiable subsurface scattering (units: mm, mm^-1).",
    )
    p.add_argument("--version", action="version", version=f"sssjax {__version__}")
    p.add_argument("--no-cache", action="store_true", help=_NO_CACHE_HELP)
    sub = p.add_subparsers(dest="command", required=True)
    # options every compiling command takes (after the command name, too)
    compiling = argparse.ArgumentParser(add_help=False)
    compiling.add_argument(
        "--no-cache", action="store_true", default=argparse.SUPPRESS, help=_NO_CACHE_HELP
    )
    # ... and every command that writes files: one overwrite rule (sssjax/_files.py)
    writing = argparse.ArgumentParser(add_help=False)
    writing.add_argument(
        "--force", action="store_true", help="overwrite existing outputs (default: refuse)"
    )

    s = sub.add_parser("materials", help="print the measured media with derived quantities")
    s.add_argument(
        "--profile",
        default="dipole",
        choices=PROFILES,
        help="diffusion profile for the total reflectance column",
    )
    s.set_defaults(func=_cmd_materials)

    s = sub.add_parser("demo", parents=[compiling, writing], help="the `make demo` job")
    s.add_argument("--out", default="out", help="output folder (default: out)")
    s.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    s.add_argument("--size", type=int, default=0, help="override the image size (pixels)")
    s.add_argument("--spp", type=int, default=0, help="override samples per pixel")
    s.set_defaults(func=_cmd_demo)

    s = sub.add_parser(
        "render",
        parents=[compiling, writing],
        help="ray trace a scene file to EXR (linear) and/or PNG (sRGB)",
    )
    s.add_argument("scene", help="scene TOML file")
    s.add_argument(
        "-o",
        "--output",
        action="append",
        default=[],
        help="output image (.exr/.png/.tif/.jpg; repeatable; "
        "default: out/SCENE.png and out/SCENE.exr)",
    )
    s.add_argument("--spp", type=int, help="samples per pixel (overrides the scene)")
    s.add_argument("--seed", type=int, help="random seed (overrides the scene)")
    s.add_argument("--width", type=int, help="image width in pixels")
    s.add_argument("--height", type=int, help="image height in pixels")
    s.add_argument("--no-sss", action="store_true", help="turn subsurface scattering off")
    s.add_argument(
        "--transport",
        help="light transport in translucent objects: diffusion (the dipole family, fast) or "
        "volumetric (exact random walks; overrides the scene's [sss] transport)",
    )
    s.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    s.add_argument(
        "--tonemap", default="clip", choices=["clip", "reinhard", "aces"], help="PNG tone mapping"
    )
    s.set_defaults(func=_cmd_render)

    s = sub.add_parser(
        "fit",
        parents=[compiling, writing],
        help="fit scattering coefficients to a target (a fit file)",
    )
    s.add_argument("fit_file", help="fit TOML file (see fits/)")
    s.add_argument("-o", "--output", help="output folder (default: the fit file's 'output')")
    s.set_defaults(func=_cmd_fit)

    s = sub.add_parser("params", help="the parameters a fit can free, with values and roles")
    s.add_argument("scene", help="scene TOML file")
    s.set_defaults(func=_cmd_params)

    s = sub.add_parser(
        "raytree",
        parents=[compiling, writing],
        help="the rays behind one pixel: JSON and a picture",
    )
    s.add_argument("scene", help="scene TOML file")
    s.add_argument("--pixel", type=int, nargs=2, metavar=("X", "Y"), required=True)
    s.add_argument("-o", "--output", help="tree JSON (default: out/SCENE_raytree_X_Y.json)")
    s.add_argument("--png", help="picture (default: out/SCENE_raytree_X_Y.png)")
    s.add_argument("--seed", type=int, help="random seed of the render (default: the scene's)")
    s.add_argument("--image", help="backdrop image (e.g. the render's EXR; default: quick render)")
    s.set_defaults(func=_cmd_raytree)

    s = sub.add_parser(
        "measure",
        parents=[compiling, writing],
        help="fit sigma_a, sigmap_s (1/mm) to the radial profile of a beam-lit image "
        "(Jensen's measurement step)",
    )
    s.add_argument("image", help="linear image (EXR/TIFF; PNG/JPEG are decoded from sRGB)")
    s.add_argument(
        "--pixel-size", type=float, help="mm per pixel on the sample (default: metadata)"
    )
    s.add_argument(
        "--center", type=float, nargs=2, metavar=("X", "Y"), help="beam centre in pixels"
    )
    s.add_argument("--eta", type=float, help="relative index of refraction (default 1.3)")
    s.add_argument("--power", type=float, help="beam power in W (default: metadata, else free)")
    s.add_argument("--free-scale", action="store_true", help="fit an intensity scale too")
    s.add_argument(
        "--r-min",
        type=float,
        help="exclude r < R_MIN mm (default: two pixels with --orders all, 1 mm with multiple)",
    )
    s.add_argument(
        "--orders",
        choices=("all", "multiple"),
        help="what the image holds: all (single + multiple scattering: a photograph, the "
        "default) or multiple (no single scattering: the default for images that sssjax's "
        "diffusion transport rendered)",
    )
    s.add_argument("--r-max", type=float, help="largest radius, mm (default: image edge)")
    s.add_argument(
        "--model",
        choices=PROFILES,
        help="profile to fit (default: tabulated, exact transport; for an image that "
        "sssjax's diffusion transport rendered, its own profile; see docs/accuracy.md)",
    )
    s.add_argument("--incidence", type=float, default=0.0, help="beam angle from normal, deg")
    s.add_argument("--view-angle", type=float, default=0.0, help="camera angle from normal")
    s.add_argument("-o", "--output", help="output folder (default: out/measure-IMAGE)")
    s.set_defaults(func=_cmd_measure)

    s = sub.add_parser(
        "preview",
        parents=[compiling],
        help="interactive previewer of a scene in the browser (viser)",
    )
    s.add_argument("scene", help="scene TOML file")
    s.add_argument("--port", type=int, default=8080, help="port (default 8080; 0: any free port)")
    s.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    s.set_defaults(func=_cmd_preview)
    return p


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as `sssjax: warning: ...`, one line (not Python's file:line and source)."""
    text = " ".join(str(message).split())
    print(f"sssjax: warning: {text}", file=sys.stderr if file is None else file, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.no_cache:
        from ._cache import disable_cache

        disable_cache()
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning
            return int(args.func(args) or 0)
    except (UserError, ValueError, FileNotFoundError, OSError) as e:
        print(f"sssjax: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sssjax: interrupted", file=sys.stderr)
        return 130
