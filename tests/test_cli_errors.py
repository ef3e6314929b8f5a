"""Issue 40 item 2: an error is one line on stderr and nothing else (no numpy warning before it, no
traceback) unless `--debug` or `OCCDATA_DEBUG=1` asks for the traceback."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cli.occdata_cli import main
from occdata.errors import OccDataError, OccDataWarning


@pytest.fixture
def world(synth_root: Path, tmp_path: Path) -> Path:
    out = tmp_path / "world"
    shutil.copytree(synth_root, out)
    return out


def _invoke(*args: str, env: dict[str, str] | None = None) -> Result:
    """The command's result; no Python warning may escape it, printed or not (the CLI prints the
    ones it shows on stderr; a warning shown the usual way is recorded here instead)."""
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")  # every warning, even one this process showed before
        r = CliRunner().invoke(main, list(args), env=env)
    assert not [w for w in shown if not issubclass(w.category, ResourceWarning)], [str(w.message) for w in shown]
    assert "Warning:" not in r.output, r.output
    return r


def _lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("labels:")]


def _huge_quaternion(world: Path) -> None:
    path = world / "v1.0-mini" / "calibrated_sensor.json"
    rows = json.loads(path.read_text())
    next(r for r in rows if r.get("camera_intrinsic"))["rotation"] = [1e300, 0.0, 0.0, 0.0]
    path.write_text(json.dumps(rows))


@pytest.mark.parametrize("command", ["scan", "build"])
def test_a_huge_quaternion_is_one_line_named_for_what_it_is(world: Path, tmp_path: Path, command: str) -> None:
    """Was: four numpy RuntimeWarnings (overflow in the norm and the matrix), then "... has NaN/inf
    values" of a finite number."""
    _huge_quaternion(world)
    args = ["--root", str(world)] if command == "scan" else ["--root", str(world), "--out",
                                                             str(tmp_path / "s.zarr"), "--no-progress"]
    r = _invoke(command, *args)
    assert r.exit_code == 1, r.output
    assert "RuntimeWarning" not in r.output and "Traceback" not in r.output, r.output
    (line,) = _lines(r.stderr)
    assert line.startswith("Error: ") and "rotation (quaternion w, x, y, z) is implausibly large (|q| = 1e+300" in line
    assert "NaN" not in line


def test_an_unexpected_error_is_one_line_and_the_traceback_only_when_asked(world: Path, monkeypatch) -> None:
    """A bug (not an OccDataError) was a bare Python traceback; now one line naming its type, message
    and frame. `--debug` or OCCDATA_DEBUG=1 print the traceback before that line."""
    import occdata.nuscenes.summary as summary

    def boom(*args, **kwargs):
        raise RuntimeError("planted bug\nits second line")

    monkeypatch.setattr(summary, "scan_tree", boom)
    r = _invoke("scan", "--root", str(world))
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    (line,) = _lines(r.stderr)
    assert line.startswith("Error: unexpected RuntimeError: planted bug at test_cli_errors.py:"), line
    assert line.endswith(" in boom (rerun with --debug or OCCDATA_DEBUG=1 for the traceback)"), line
    for debug in (_invoke("--debug", "scan", "--root", str(world)),
                  _invoke("scan", "--root", str(world), env={"OCCDATA_DEBUG": "1"})):
        assert debug.exit_code == 1, debug.output
        lines = _lines(debug.stderr)
        assert lines[0] == "Traceback (most recent call last):" and "RuntimeError: planted bug" in debug.stderr
        assert lines[-1] == line


def test_debug_shows_the_traceback_of_our_own_errors_too(world: Path) -> None:
    _huge_quaternion(world)
    plain = _invoke("scan", "--root", str(world))
    debug = _invoke("--debug", "scan", "--root", str(world))
    assert debug.exit_code == plain.exit_code == 1
    assert "Traceback" in debug.stderr and "occdata.errors.OccDataError" in debug.stderr
    assert _lines(debug.stderr)[-1] == _lines(plain.stderr)[0]
    assert "RuntimeWarning" not in debug.output


def test_our_warnings_are_one_line_each(world: Path, monkeypatch) -> None:
    import occdata.nuscenes.summary as summary

    def note_then_fail(*args, **kwargs):
        warnings.warn(OccDataWarning("the lease is checked, then written"), stacklevel=2)
        raise OccDataError("planted")

    monkeypatch.setattr(summary, "scan_tree", note_then_fail)
    r = _invoke("scan", "--root", str(world))
    assert _lines(r.stderr) == ["warning: the lease is checked, then written", "Error: planted"], r.stderr
