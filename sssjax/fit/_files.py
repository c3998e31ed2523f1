"""Fit files (`sssjax fit FIT.toml`): a scene, a target, the free parameters, starting values
and options, read and validated into a `FitJob`."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from .. import params as _params
from .._fitfile import check_fit_file
from .._registry import did_you_mean
from ..scene import Scene, load_scene, read_toml
from ._options import FitOptions
from ._problem import FitProblem
from ._result import FitError

__all__ = ["FitJob", "load_fit_file"]

_FIT_KEYS = {"scene", "target", "synthetic", "params", "init", "settings", "solver", "output"}
# `[solver]`: every `FitOptions` field (`method` names the solver), and the trace seed
_SOLVER_KEYS = {"method", "seed"} | {f.name for f in dataclasses.fields(FitOptions)} - {"solver"}
_SYNTH_KEYS = {"seed", "transport", "spp"}


@dataclasses.dataclass
class FitJob:
    """A parsed fit file: everything `fit` needs, plus where results go."""

    path: Path
    scene: Scene
    target: Any  # a path, or None for a synthetic target
    synthetic_seed: int | None
    params: list[str] | None
    init: dict[str, Any]
    seed: int | None
    output: Path
    options: FitOptions = dataclasses.field(default_factory=FitOptions)
    # the scene the synthetic target is rendered from (its `[synthetic]` transport / spp)
    synthetic_scene: Any = None

    def fit_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of `fit` this file sets."""
        return dict(params=self.params, init=self.init, seed=self.seed, options=self.options)


def load_fit_file(path: str | Path) -> FitJob:
    """Read and validate a fit file (TOML). Relative paths resolve against its folder.

    Keys: `scene` (path), `target` (image path) or `[synthetic] seed = S` (render the target
    from the scene's own media with seed S: a recovery check; `transport` and `spp` there
    render it with another transport than the fit's, e.g. an exact `"volumetric"` target
    for a `"diffusion"` fit, and other samples per pixel), `params` (list of parameter
    names, `sssjax.params`), `[init]` (starting values by parameter name, mm^-1),
    `[settings]` (scene overrides: `width`, `height`, `spp`, `light_samples`,
    `sss_cloud_size`, ...), `[solver]` (`method` lm|gn|bfgs, `seed`, and the other
    `FitOptions`: `max_steps`, `rtol`, `atol`, `loss` l2|cauchy|huber, `loss_scale`,
    `weighting` absolute|relative, `rel_floor`, `traces`, `refine`, `proposal_rounds`,
    `proposal_tol`, `instruments` diffusion|smoothed), `output` (folder).
    """
    path = Path(path)
    d = read_toml(path, FitError, "fit file")

    def unknown(keys, known, where):
        for k in keys:
            if k not in known:
                hint = did_you_mean(k, sorted(known))
                raise FitError(f"{path}: {where}{k}: unknown key{hint}")

    unknown(d, _FIT_KEYS, "")
    check_fit_file(path, d, FitError)  # types and ranges, one line naming table and key
    if "scene" not in d:
        raise FitError(f"{path}: scene: missing required key")
    if ("target" in d) == ("synthetic" in d):
        raise FitError(f"{path}: give exactly one of 'target' (an image) and [synthetic]")
    base = path.parent
    scene = load_scene(base / d["scene"])
    settings = d.get("settings", {})
    try:
        scene = scene.with_settings(**settings) if settings else scene
    except (TypeError, ValueError) as e:
        raise FitError(f"{path}: [settings]: {e}") from None
    solver = dict(d.get("solver", {}))
    unknown(solver, _SOLVER_KEYS, "[solver] ")
    synth = d.get("synthetic")
    synth_scene = None
    if synth is not None:
        unknown(synth, _SYNTH_KEYS, "[synthetic] ")
        names = {"transport": "sss_transport", "spp": "spp"}
        over = {names[k]: v for k, v in synth.items() if k in names}
        try:
            synth_scene = scene.with_settings(**over) if over else scene
        except (TypeError, ValueError) as e:
            raise FitError(f"{path}: [synthetic]: {e}") from None
    params = d.get("params")
    if params is not None and (
        not isinstance(params, list) or not all(isinstance(p, str) for p in params)
    ):
        raise FitError(f"{path}: params: expected a list of names like 'marble.sigma_a'")
    init = dict(d.get("init", {}))
    for where, names in (("params", params or []), ("[init]", init)):
        for name in names:
            try:
                _params.canonical(scene, name)
            except _params.ParameterError as e:
                raise FitError(f"{path}: {where}: {e}") from None
    seed = solver.pop("seed", None)
    if "method" in solver:
        solver["solver"] = solver.pop("method")
    try:
        options = FitOptions(**solver)
    except FitError as e:
        raise FitError(f"{path}: [solver]: {e}") from None
    try:  # what `fit` checks of the parameters, before a synthetic target is rendered
        FitProblem.checked_params(scene, params, init, options)
    except FitError as e:
        raise FitError(f"{path}: {e}") from None
    return FitJob(
        path=path,
        scene=scene,
        target=(base / d["target"]) if "target" in d else None,
        synthetic_seed=int(synth.get("seed", 1)) if synth is not None else None,
        synthetic_scene=synth_scene,
        params=params,
        init=init,
        seed=seed,
        output=Path(d["output"]) if "output" in d else Path("out") / "fits" / path.stem,
        options=options,
    )
