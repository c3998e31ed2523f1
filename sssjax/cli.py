"""The `sssjax` command line: `sssjax materials`, `sssjax demo`, ...

User mistakes (bad files, bad values) print one line `sssjax: error: ...` and exit with
status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


class UserError(Exception):
    """An error caused by the user's input: reported in one line, without a traceback."""


def materials_table() -> str:
    """The measured presets with their derived quantities, as a fixed-width text table."""
    from .dipole import Rd_total
    from .media import preset, preset_names

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
            f"{trip(Rd_total(m.sigma_a, m.sigmap_s, m.eta), '{:5.3f}'):<19} "
            f"{trip(m.diffuse_mean_free_path, '{:6.2f}'):<22}"
        )
    lines.append("(Jensen et al. 2001; g = 0, eta = 1.3; total R_d of the classic dipole)")
    return "\n".join(lines)


def _cmd_materials(args: argparse.Namespace) -> int:
    print(materials_table())
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .plots import plot_profiles

    out = Path(args.out)
    print(materials_table())
    path = plot_profiles(
        ["marble", "skimmilk", "ketchup", "skin1", "wholemilk", "apple"], out / "rd_profiles.png"
    )
    print(f"\nwrote the R_d(r) plot to {path.resolve()}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from ._version import __version__

    p = argparse.ArgumentParser(
        prog="sssjax",
        description="Differentiable subsurface scattering (units: mm, mm^-1).",
    )
    p.add_argument("--version", action="version", version=f"sssjax {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("materials", help="print the measured media with derived quantities")
    s.set_defaults(func=_cmd_materials)

    s = sub.add_parser("demo", help="the `make demo` job")
    s.add_argument("--out", default="out", help="output folder (default: out)")
    s.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, ValueError, FileNotFoundError) as e:
        print(f"sssjax: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sssjax: interrupted", file=sys.stderr)
        return 130
