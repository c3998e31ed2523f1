"""Types and ranges of a fit file's keys (`sssjax fit FIT.toml`), checked with the scene
file's own checkers so that a mistake is one line naming the file, table and key:
`f.toml: [solver] max_steps: must be >= 1, got 0`. Unknown keys are left to the loader
(`sssjax.fit.load_fit_file`), which suggests the closest known one.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .scene import _bool, _fmt, _nonneg_int, _number, _pos, _pos_int, _str

__all__ = ["check_fit_file"]


class _Ctx:
    def __init__(self, path: Path, table: str, error: type[Exception]):
        self.path, self.table, self.error = path, table, error

    def err(self, field: str | None, msg: str) -> Exception:
        where = f"[{self.table}] " if self.table else ""
        return self.error(f"{self.path}: {where}{field}: {msg}")


def _init_value(ctx, name, v):
    if isinstance(v, list | tuple):
        if len(v) != 3:
            raise ctx.err(name, f"expected a number or a list of 3 numbers (RGB), got {_fmt(v)}")
        return [_number(ctx, name, x) for x in v]
    return _number(ctx, name, v)


_TOP = {"scene": _str, "target": _str, "output": _str}
_SOLVER = {
    "method": _str,
    "max_steps": _pos_int,
    "seed": _nonneg_int,
    "rtol": _pos,
    "atol": _pos,
    "loss": _str,
    "loss_scale": _pos,
    "weighting": _str,
    "rel_floor": _pos,
    "traces": _pos_int,
    "refine": _bool,
    "proposal_rounds": _nonneg_int,
    "proposal_tol": _pos,
    "instruments": _str,
}
_SYNTHETIC = {"seed": _nonneg_int, "transport": _str, "spp": _pos_int}


def check_fit_file(path: str | Path, d: Mapping[str, Any], error: type[Exception]) -> None:
    """Check the known keys of a parsed fit file `d` read from `path`.

    **Raises:** `error` with a one-line message naming `path`, the table and the key.
    """
    path = Path(path)
    top = _Ctx(path, "", error)
    for key, check in _TOP.items():
        if key in d:
            check(top, key, d[key])
    for table in ("settings", "init", "solver", "synthetic"):
        if table in d and not isinstance(d[table], Mapping):
            raise top.err(table, f"expected a table [{table}], got {_fmt(d[table])}")
    init = _Ctx(path, "init", error)
    for key, v in d.get("init", {}).items():
        _init_value(init, key, v)
    for table, schema in (("solver", _SOLVER), ("synthetic", _SYNTHETIC)):
        ctx = _Ctx(path, table, error)
        for key, v in d.get(table, {}).items():
            if key in schema:
                schema[key](ctx, key, v)
