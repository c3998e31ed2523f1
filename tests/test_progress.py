"""Progress: a live bar on a terminal, a few whole lines in a file or pipe."""

import io
import tomllib
from pathlib import Path

import sssjax
from sssjax._progress import Progress, is_terminal

DATA = Path(__file__).parent / "data"


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_plain_lines_in_a_file_are_few_and_whole():
    out = io.StringIO()
    bar = Progress(200, "rendering", file=out)
    for done in range(1, 201):
        bar.update(done)
    text = out.getvalue()
    lines = text.splitlines()
    assert "\r" not in text
    assert 3 <= len(lines) <= 6, lines  # the first, each quarter, the last
    assert lines[0].startswith("rendering: 1/200 tiles")
    assert lines[-1].startswith("rendering: 200/200 tiles (100%)")
    assert "left" in lines[1]  # an estimate of the time left on the way


def test_live_bar_on_a_terminal():
    out = Terminal()
    assert is_terminal(out) and not is_terminal(io.StringIO())
    bar = Progress(50, "fitting", file=out, unit="steps")
    for done in range(1, 51):
        bar.update(done, loss=1.0 / done)
    text = out.getvalue()
    assert "\r" in text  # redrawn in place (tqdm)
    assert "50/50" in text.rsplit("\r", 1)[-1] and "fitting" in text


def test_every_line_mode_and_disabled():
    out = io.StringIO()
    bar = Progress(5, "fitting", file=out, every_line=True)
    for n in range(0, 4):
        bar.update(n, line=f"step {n}", loss=0.1)
    bar.close()
    assert out.getvalue().splitlines() == [f"step {n}" for n in range(4)]
    quiet = io.StringIO()
    Progress(5, "x", enabled=False, file=quiet).update(5)
    assert quiet.getvalue() == ""


def test_render_progress_to_a_pipe_is_a_few_lines(capsys):
    d = tomllib.loads((DATA / "tiny_scene.toml").read_text())
    d["render"]["tile"] = 1  # 64 tiles of one pixel
    d["materials"]["marble"] = {"type": "diffuse", "albedo": 0.5}
    scene = sssjax.load_scene(d)
    sssjax.render(scene, 0, progress=True)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("rendering")]
    assert 2 <= len(lines) <= 6, err
    assert lines[-1].startswith("rendering: 64/64 tiles (100%)")
