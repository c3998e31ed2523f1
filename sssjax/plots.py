"""Pictures: diffusion profiles, convergence plots. matplotlib with the Agg backend (no screen)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

_RGB = ("#d62728", "#2ca02c", "#1f77b4")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_profiles(names: Sequence[str], path: str | Path, r_max_mm: float = 20.0) -> Path:
    """Plot `R_d(r)` (log scale, mm^-2) against r (mm) per RGB channel for named presets.

    **Arguments:** `names` of presets; `path` of the PNG to write; `r_max_mm` the range.

    **Returns:** the path written.
    """
    from .dipole import Rd
    from .media import preset

    plt = _pyplot()
    r = np.linspace(0.0, r_max_mm, 400)
    n = len(names)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax, name in zip(axes.ravel(), names, strict=False):
        m = preset(name)
        prof = np.asarray(Rd(r[:, None], m.sigma_a, m.sigmap_s, m.eta))
        for c in range(3):
            ax.semilogy(r, prof[:, c], color=_RGB[c], label="RGB"[c])
        ax.set_title(name)
        ax.set_xlabel("r [mm]")
        ax.set_ylabel("R_d(r) [mm$^{-2}$]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.suptitle("Classic dipole diffuse reflectance profiles (Jensen et al. 2001 media)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
