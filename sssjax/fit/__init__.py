"""Fitting scattering coefficients to images: where the measurement happens.

`fit(scene, target, ...)` traces the scene once (`trace`) and then runs a least-squares
solver (Levenberg-Marquardt by default, `SOLVERS`) on pixel residuals of `shade`, in the log
of the coefficients, with forward-mode Jacobians (few parameters, many pixels). Every
iteration only re-shades: no ray is cast inside the loop. The result carries standard
errors from the Gauss-Newton covariance `s^2 (J^T J)^-1` at the solution (mapped from log
space by the delta method), the correlation matrix, the history and the solver's status.

The modules: `_problem` (the `FitProblem`: target, free parameters and their coordinates,
traced data, residuals), `_solve` (the solver loop and the phases: `eta` search, relative
reweighting, `refine`), `_report` (covariance, warnings, `FitResult`), `_options`
(`FitOptions` with the defaults, and the registries of solvers, losses and weightings),
`_files` (fit files), `_result` (`FitResult`, `FitError`). Parameter names are
`sssjax.params`'. Coefficients in mm^-1.
"""

from ..params import PARAM_FIELDS
from ._files import FitJob, load_fit_file
from ._fit import fit
from ._options import LOSSES, SOLVERS, WEIGHTINGS, FitOptions
from ._result import FitError, FitResult

__all__ = [
    "fit",
    "FitResult",
    "FitError",
    "FitOptions",
    "FitJob",
    "load_fit_file",
    "PARAM_FIELDS",
    "SOLVERS",
    "LOSSES",
    "WEIGHTINGS",
]
