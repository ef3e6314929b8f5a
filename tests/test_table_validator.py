"""One reading of the tables for every command: `occdata scan`, `build` and `labels` refuse the same broken
trees with the same one line (issue 40 item 1). Each case is a copy of the small synthetic world with one
edit; the message must name the table, row and field, and nothing else may be printed to stderr."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.occdata_cli import main

V = "v1.0-mini"
Rows = list[dict]


def _edit(root: Path, table: str, fn: Callable[[Rows], None]) -> None:
    path = root / V / f"{table}.json"
    rows = json.loads(path.read_text())
    fn(rows)
    path.write_text(json.dumps(rows))


def _sample_prev(rows: Rows) -> None:
    rows[1]["prev"] = "f" * 32


def _sd_next(rows: Rows) -> None:
    next(r for r in rows if r["is_key_frame"] and r["next"])["next"] = "e" * 32


def _sd_prev(rows: Rows) -> None:
    next(r for r in rows if r["is_key_frame"] and r["prev"])["prev"] = "e" * 32


def _no_scenes(rows: Rows) -> None:
    rows.clear()


def _no_next(rows: Rows) -> None:
    del rows[0]["next"]


def _dropped_duplicate(rows: Rows) -> None:
    # a non-keyframe row (build and labels without sweeps never keep it) written twice, differently
    copy = dict(next(r for r in rows if not r["is_key_frame"]))
    copy["timestamp"] += 1
    rows.append(copy)


def _negative_timestamp(rows: Rows) -> None:
    rows[0]["timestamp"] = -5


E32, F32 = "e" * 32, "f" * 32
CASES = {
    "sample prev nowhere": ("sample", _sample_prev, f"prev is '{F32}', but the scene's order"),
    "sample_data next nowhere": ("sample_data", _sd_next, f".next refers to sample_data '{E32}', not in sample_data"),
    "sample_data prev nowhere": ("sample_data", _sd_prev, f".prev refers to sample_data '{E32}', not in sample_data"),
    "no scenes": ("scene", _no_scenes, "scene.json holds no scenes: nothing to read"),
    "sample without next": ("sample", _no_next, "has no field 'next'"),
    "dropped row twice": ("sample_data", _dropped_duplicate, "twice with different content (fields 'timestamp'"),
    "negative timestamp": ("sample", _negative_timestamp, "timestamp is negative (-5)"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_scan_build_and_labels_refuse_alike(synth_root: Path, tmp_path: Path, case: str) -> None:
    table, fn, message = CASES[case]
    root = tmp_path / "tree"
    shutil.copytree(synth_root, root, symlinks=True)
    _edit(root, table, fn)
    runner = CliRunner()
    for args in (["scan", "--root", str(root)],
                 ["build", "--root", str(root), "--out", str(tmp_path / "s.zarr"), "--no-progress"],
                 ["labels", "--root", str(root), "--out", str(tmp_path / "gts"), "--no-progress"]):
        res = runner.invoke(main, args)
        assert res.exit_code == 1, (args[0], res.output)
        errors = [line for line in res.output.splitlines() if line.startswith("Error")]
        assert len(errors) == 1 and message in errors[0], (args[0], res.output)
        assert "Traceback" not in res.output and "Warning" not in res.output


def test_a_box_of_implausible_size_is_refused_by_scan_and_labels(synth_root: Path, tmp_path: Path) -> None:
    root = tmp_path / "tree"
    shutil.copytree(synth_root, root, symlinks=True)

    def huge(rows: Rows) -> None:
        rows[0]["size"] = [1e300, 2.0, 2.0]

    _edit(root, "sample_annotation", huge)
    for args in (["scan", "--root", str(root)],
                 ["labels", "--root", str(root), "--out", str(tmp_path / "gts"), "--no-progress"]):
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 1, res.output
        assert "size [1e+300, 2.0, 2.0] is not a plausible box size (over 100 m)" in res.output
