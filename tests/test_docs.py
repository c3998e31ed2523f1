"""Documentation that runs: every ```python block of README.md and docs/*.md is executed
(the blocks of one file in order, sharing their names, as a reader would type them), and
every `sssjax ...` command of the shell blocks is parsed by the command line's own parser,
so that an example can never drift from the API again.

The Python blocks run in a temporary folder where `scenes/` and `fits/` are the repository's,
with `sssjax.load_scene` shrinking each scene (an eighth of the resolution, at most 2 spp, a
small irradiance cloud) and `sssjax.raytree` mapping a full-resolution pixel to the same
place of the shrunk image: the blocks run as written, in seconds instead of minutes. The
"photograph" a block fits (`photo.exr`) is rendered from the shrunk scene beforehand.
"""

import math
import re
import shlex
from pathlib import Path

import pytest

import sssjax

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "fits" / "README.md"]
SHRINK = 8
FENCE = re.compile(r"^```(\w*)\s*$")


def code_blocks(path: Path, langs: tuple[str, ...]) -> list[tuple[int, str]]:
    """The fenced blocks of `path` in one of `langs`: `(first line number, code)`."""
    out, lang, start, lines = [], None, 0, []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        m = FENCE.match(line.strip())
        if lang is None and m and m.group(1):
            lang, start, lines = m.group(1), i + 1, []
        elif lang is not None and line.strip() == "```":
            if lang in langs:
                out.append((start, "\n".join(lines)))
            lang = None
        elif lang is not None:
            lines.append(line)
    return out


PY_DOCS = [p for p in DOCS if p.exists() and code_blocks(p, ("python",))]


@pytest.fixture
def shrunk(monkeypatch, tmp_path):
    """Scenes at an eighth of their size; raytree pixels mapped to match."""
    real_load, real_raytree = sssjax.load_scene, sssjax.raytree
    factors: dict[int, tuple] = {}

    def load_scene(source, **kw):
        scene = real_load(source, **kw)
        cam = scene.camera
        w, h = max(8, math.ceil(cam.width / SHRINK)), max(8, math.ceil(cam.height / SHRINK))
        small = scene.with_settings(
            width=w,
            height=h,
            spp=min(scene.render.spp, 2),
            light_samples=1,
            sss_cloud_size=min(scene.sss.cloud_size, 512),
        )
        factors[id(small)] = (small, cam.width / w, cam.height / h)
        return small

    def raytree(scene, pixel, *args, **kw):
        _, fx, fy = factors.get(id(scene), (None, 1.0, 1.0))
        return real_raytree(scene, (int(pixel[0] / fx), int(pixel[1] / fy)), *args, **kw)

    monkeypatch.setattr(sssjax, "load_scene", load_scene)
    monkeypatch.setattr(sssjax, "raytree", raytree)
    for name in ("scenes", "fits"):
        (tmp_path / name).symlink_to(ROOT / name)
    monkeypatch.chdir(tmp_path)
    # the user's photograph of the marble cube, for the fitting example
    photo = sssjax.render(load_scene("scenes/marble_cube.toml"), 1)
    sssjax.imageio.write_image(tmp_path / "photo.exr", photo)
    return tmp_path


@pytest.mark.parametrize("doc", PY_DOCS, ids=[p.relative_to(ROOT).as_posix() for p in PY_DOCS])
def test_python_blocks_run(doc, shrunk):
    namespace: dict = {"__name__": "__doc_example__"}
    blocks = code_blocks(doc, ("python",))
    assert blocks
    for line, code in blocks:
        # padded so that a traceback names the documentation's own line
        exec(compile("\n" * (line - 1) + code, str(doc), "exec"), namespace)
    if doc.name == "README.md":  # what the blocks promise, checked
        assert (shrunk / "cube.exr").exists() and (shrunk / "result.json").exists()
        assert namespace["image"].shape == (32, 32, 3)
        assert namespace["grad"].shape == (3,)


def shell_commands(path: Path) -> list[tuple[int, list[str]]]:
    """Every `sssjax ...` line of the shell blocks of `path`, as argv (comments and the
    `[...]` of optional parts dropped)."""
    out = []
    for start, code in code_blocks(path, ("sh", "bash", "console", "shell")):
        for k, line in enumerate(code.splitlines()):
            line = line.split(" #", 1)[0].strip().removeprefix("$ ")
            if line.startswith("sssjax "):
                words = shlex.split(line.replace("[", " ").replace("]", " "))
                out.append((start + k, words[1:]))
    return out


SHELL = [(p, n, argv) for p in DOCS if p.exists() for n, argv in shell_commands(p)]


@pytest.mark.parametrize("doc,line,argv", SHELL, ids=[f"{p.name}:{n}" for p, n, _ in SHELL])
def test_shell_commands_parse(doc, line, argv, capsys):
    from sssjax.cli import build_parser

    try:
        build_parser().parse_args(argv)
    except SystemExit:
        pytest.fail(f"{doc.name}:{line}: sssjax {' '.join(argv)}: {capsys.readouterr().err}")


INLINE = re.compile(r"`(sssjax [^`]*)`")


def test_inline_commands_name_real_subcommands_and_flags():
    """`sssjax CMD --flag` in running text: CMD exists and has every flag named."""
    from sssjax.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    top_flags = {o for a in parser._actions for o in a.option_strings}
    seen = 0
    for doc in DOCS:
        if not doc.exists():
            continue
        for m in INLINE.finditer(doc.read_text()):
            words = [w for w in m.group(1).split()[1:] if w != "..."]
            while words and words[0].startswith("-"):  # options before the command
                assert words.pop(0) in top_flags, (doc.name, m.group(1))
            if not words:
                continue
            assert words[0] in sub.choices, (doc.name, m.group(1))
            flags = {o for a in sub.choices[words[0]]._actions for o in a.option_strings}
            for w in words[1:]:
                if w.startswith("-"):
                    assert w.split("=")[0] in flags, (doc.name, m.group(1), w)
            seen += 1
    assert seen >= 5
