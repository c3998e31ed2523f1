"""Never lose a file: one overwrite rule and atomic writes for every output.

- `check_outputs(paths, force=..., inputs=...)`: the rule of every command, checked before
  any work starts: an existing output is refused unless `force`; an input (a scene, an OBJ
  mesh, a target or backdrop image) is never an output, `force` or not.
- `atomic(path)`: a context manager yielding a temporary path in the same folder (same
  suffix, so writers that go by the extension pick the format); on success it is renamed
  over `path` with `os.replace` (atomic on POSIX and Windows), on any failure (an exception,
  Ctrl-C) it is deleted: an interrupted run leaves the old file, or none, never half a file.
  With `overwrite=False` the rename refuses an existing file (a hard link, which fails
  rather than replace), for the previewer's saves.
- `write_text`, `write_bytes`, `save_figure`: atomic writes of text, bytes and matplotlib
  figures; images go through `sssjax.imageio.write_image`, which uses `atomic` too.
- `free_stem(base, suffixes, protect)`: the previewer's rule: `base`, else `base_1`,
  `base_2`, ... whichever has none of its files on disk.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path

__all__ = [
    "OutputExistsError",
    "check_outputs",
    "scene_inputs",
    "atomic",
    "write_text",
    "write_bytes",
    "save_figure",
    "free_stem",
    "is_temporary",
]

_TMP_TAG = ".sssjax-tmp-"


class OutputExistsError(FileExistsError):
    """An output file exists and may not be overwritten (reported in one line)."""


def _same(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(
    paths: Iterable[str | os.PathLike],
    *,
    force: bool,
    inputs: Iterable[str | os.PathLike] = (),
) -> list[Path]:
    """Refuse outputs that would overwrite an input (always) or an existing file (unless
    `force`), and outputs named twice; call it before the work that produces them.

    **Arguments:** `paths` the outputs; `force` whether existing outputs may be replaced;
    `inputs` files the command reads (never replaced).

    **Returns:** the outputs as `Path`s.

    **Raises:** `ValueError` for an input or a repeated output, `OutputExistsError` (one
    line naming every existing output and `--force`) otherwise.
    """
    outs = [Path(p) for p in paths]
    ins = [Path(p) for p in inputs]
    for i, out in enumerate(outs):
        for inp in ins:
            if _same(out, inp):
                raise ValueError(
                    f"refusing to overwrite the input file {out} (choose another output)"
                )
        for other in outs[:i]:
            if _same(out, other):
                raise ValueError(f"the output {out} is named twice")
        if out.is_dir():
            raise ValueError(f"the output {out} is a folder")
        for parent in out.absolute().parents:
            if parent.exists():
                if not parent.is_dir():
                    raise ValueError(f"cannot write {out}: {parent} is a file, not a folder")
                break
    existing = [str(p) for p in outs if p.exists()]
    if existing and not force:
        also = f" and {', '.join(existing[1:])}" if len(existing) > 1 else ""
        raise OutputExistsError(
            f"{existing[0]} exists; use --force to overwrite it{also} (or choose another output)"
        )
    return outs


def scene_inputs(scene) -> list[Path]:
    """The files a scene was read from (the scene file and its OBJ meshes): never outputs."""
    paths = [Path(scene.path)] if scene.path else []
    for raw in (scene.source or {}).get("shapes", []):
        if isinstance(raw, dict) and isinstance(raw.get("file"), str):
            paths.append(Path(scene.path or ".").parent / raw["file"])
    return paths


def is_temporary(path: str | os.PathLike) -> bool:
    """Whether `path` is one of `atomic`'s temporary files (left only by a killed process)."""
    return _TMP_TAG in Path(path).name


@contextlib.contextmanager
def atomic(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Write `path` all at once: yields a temporary path next to it to write to.

    **Arguments:** `path` the file to (re)place; missing parent folders are created.
    `overwrite=False`: fail with `FileExistsError` rather than replace an existing file
    (checked atomically where the filesystem has hard links).

    **Raises:** whatever the body raises (the temporary file is removed first).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}{_TMP_TAG}{secrets.token_hex(4)}{path.suffix}")
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"{path}: nothing was written")
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # fails if `path` exists: never replaces a file
            except FileExistsError:
                raise FileExistsError(f"{path} exists; not overwritten") from None
            except OSError:  # no hard links here (some network or FAT filesystems)
                if path.exists():
                    raise FileExistsError(f"{path} exists; not overwritten") from None
                os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path: str | os.PathLike, text: str, *, overwrite: bool = True) -> Path:
    """Write `text` (UTF-8) to `path` atomically (see `atomic`). **Returns:** the path."""
    with atomic(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> Path:
    """Write `data` to `path` atomically (see `atomic`). **Returns:** the path."""
    with atomic(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def save_figure(fig, path: str | os.PathLike, **savefig_kw) -> Path:
    """`fig.savefig(path, ...)` atomically, in the format of `path`'s extension.

    **Returns:** the path."""
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower() or None
    with atomic(path) as tmp:
        fig.savefig(tmp, format=fmt, **savefig_kw)
    return path


def free_stem(
    base: str | os.PathLike, suffixes: Iterable[str], protect: Iterable[str | os.PathLike] = ()
) -> dict[str, Path]:
    """Free output names `{stem}{suffix}` next to `base` for every suffix: `base`'s own stem
    if none of them exists (or is in `protect`), else `stem_1`, `stem_2`, ...

    **Returns:** the paths by suffix (without its dot).

    **Raises:** `FileExistsError` when 10000 stems are taken.
    """
    base = Path(base)
    suffixes = list(suffixes)
    protected = [Path(p) for p in protect]
    for n in range(10_000):
        stem = base.name if n == 0 else f"{base.name}_{n}"
        paths = {s.lstrip("."): base.with_name(f"{stem}{s}") for s in suffixes}
        taken = any(p.exists() or any(_same(p, q) for q in protected) for p in paths.values())
        if not taken:
            return paths
    raise FileExistsError(f"{base}: no free output name after 10000 tries")
