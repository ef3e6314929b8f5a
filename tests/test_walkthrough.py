"""benchmarks/walkthrough.py: the pieces its figures come from (byte counts, the linear fit, the command
runner), and one small run on the replayed real keyframe (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.common import REAL_NUSCENES
from benchmarks.walkthrough import linear_fit, run_command, tree_bytes


def test_tree_bytes_counts_files_not_links(tmp_path: Path) -> None:
    (tmp_path / "a").write_bytes(b"x" * 1000)
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "b").write_bytes(b"y" * 24)
    (tmp_path / "link").symlink_to(tmp_path / "a")  # a replayed tree links the real files: not its bytes
    got = tree_bytes(tmp_path)
    assert got["apparent"] == 1024
    assert got["disk"] >= 1024 and got["disk"] % 512 == 0


def test_linear_fit_recovers_fixed_and_per_sample_cost() -> None:
    def size(n: int) -> dict:
        wall = 10.0 + 0.02 * n
        return {"samples": n, "build": {"wall_s": wall, "cpu_s": 2 + 0.05 * n},
                "verify": {"wall_s": 2 * wall, "cpu_s": 0.03 * n},
                "first_batch": {"wall_s": 3.0 + 0.001 * n, "cpu_s": 1.0 + 0.0003 * n}}

    fit = linear_fit([size(300), size(1200)])
    assert fit["build_wall"] == pytest.approx({"fixed_s": 10.0, "per_sample_s": 0.02})
    assert fit["build_cpu"] == pytest.approx({"fixed_s": 2.0, "per_sample_s": 0.05})
    assert fit["verify_wall"] == pytest.approx({"fixed_s": 20.0, "per_sample_s": 0.04})
    assert fit["verify_cpu"] == pytest.approx({"fixed_s": 0.0, "per_sample_s": 0.03}, abs=1e-9)
    assert fit["first_batch_wall"] == pytest.approx({"fixed_s": 3.0, "per_sample_s": 0.001})
    assert fit["first_batch_cpu"] == pytest.approx({"fixed_s": 1.0, "per_sample_s": 0.0003})


def test_run_command_reports_cpu_rss_and_output() -> None:
    res = run_command(["json.tool", "--help"])
    assert "usage" in res["stdout"] and res["cpu_s"] > 0 and res["peak_rss_mib"] > 1 and res["wall_s"] > 0
    with pytest.raises(SystemExit, match="failed"):
        run_command(["json.tool", "/nonexistent/file.json"])


@pytest.mark.slow
def test_small_walkthrough_on_the_replayed_keyframe(tmp_path: Path) -> None:
    if not REAL_NUSCENES.is_dir():
        pytest.skip("the real nuScenes keyframe (../shared/data) is not here")
    out = tmp_path / "w.json"
    run_command(["benchmarks.walkthrough", "--sizes", "60,90", "--no-labels", "--json", str(out)])
    result = json.loads(out.read_text())
    a, b = result["sizes"]
    assert (a["samples"], b["samples"]) == (60, 90) and a["train_samples"] == 30
    # the store keeps the original JPEG bytes and the projected points: below the input, above the JPEGs alone
    assert 0.3 < a["store_bytes_per_sample"]["apparent"] / result["input_bytes_per_sample"] < 1.2
    assert b["build"]["samples_per_s"] > 0 and b["verify"]["samples_per_s"] > 0
    assert b["first_batch"]["wall_s"] > 0 and b["first_batch"]["cpu_s"] > 0
    assert set(result["fit"]) == {f"{s}_{k}" for s in ("build", "verify", "first_batch") for k in ("wall", "cpu")}
