"""benchmarks.bench_scale plumbing (no timing asserts): every figure of issue 33's table is present for a
build in this process and on a 2-worker LocalCluster, and the table prints."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import bench_scale as bs
from benchmarks import scale_meter, scale_profile


def test_block_ceiling_follows_dask_greedy_order() -> None:
    assert bs.block_ceiling([32] * 7 + [16], 2) == pytest.approx(240 / 128)  # 240 samples in blocks of 32
    assert bs.block_ceiling([24] * 10, 2) == 2.0
    assert bs.block_ceiling([2, 2, 2], 2) == 1.5
    assert bs.block_ceiling([40] * 6, 1) == 1.0


def test_first_call_notes_once_and_restores() -> None:
    import occdata.store.build as build

    original = build.run_tasks
    with scale_meter.first_call() as seen:
        assert build.run_tasks is not original and not seen
    assert build.run_tasks is original

    def work() -> int:
        sum(range(10**6))
        return 4

    rec = scale_meter.measure(work)
    assert rec["units"] == 4 and rec["client_share"] == pytest.approx(1.0) and "first_task_s" not in rec


def test_strace_and_perf_summaries_are_read(tmp_path: Path) -> None:
    (tmp_path / "s.txt").write_text("% time     seconds  usecs/call     calls    errors syscall\n"
                                    "------ ----------- ----------- --------- --------- ----------------\n"
                                    " 90.00    1.000000          10    100000      5000 futex\n")
    assert scale_profile.summary_lines(tmp_path / "s.txt", "strace")[-1].endswith("futex")
    counter = "  1234.5 msec task-clock   #  1.1 CPUs utilized"
    (tmp_path / "p.txt").write_text(f"# started on ...\n\n{counter}\n")
    assert scale_profile.summary_lines(tmp_path / "p.txt", "perf") == [counter]
    assert set(scale_profile.available_profilers()) <= set(scale_profile.PROFILERS)


def test_build_figures_at_one_and_two_workers(synth_root: Path, tmp_path: Path) -> None:
    args = bs.parse_args(["--root", str(synth_root), "--gts", str(synth_root / "gts"), "--block-samples", "2",
                          "--lidar-sweeps", "2", "--sections", "bytes,build", "--workers", "1", "2"])
    world = bs.World.of(args.root, args.gts)
    saved: list[list[str]] = []
    res = bs.run_sections(args, world, tmp_path, lambda r: saved.append(sorted(r)))
    assert saved == [["bytes", "world"], ["build", "bytes", "world"]]  # after each section
    assert res["world"]["samples"] == 6 and res["world"]["image_size"][0] > 0
    build = res["build"]
    assert build["ceiling_2_over_1"] == 1.5 and build["speedup_2_over_1"] > 0
    assert build["dask_overhead"]["seconds_per_task"] > 0 and build["localcluster_2_startup_s"] > 0
    one, two = build["workers_1"], build["workers_2"]
    for rec in (one, two):
        assert rec["units"] == 6 and rec["units_per_s"] > 0 and len(rec["seconds_all"]) == 1
        assert rec["cpu_s_per_unit"]["user"] > 0 and 0 <= rec["kernel_share"] <= 1
        assert rec["first_task_s"] >= 0 and rec["client_cpu_before_first_task_s"] >= 0
        assert rec["written_over_stored"] > 0.5 and rec["stored_bytes_per_unit"] > 0
    assert one["client_share"] == pytest.approx(1.0) and one["cpu_s"]["workers"]["user"] == 0
    assert two["tasks"] == 3 and 0 < two["worker_busy_share"] <= 1 and two["cpu_s"]["workers"]["user"] > 0
    assert len(two["worker_peak_rss_mib"]) == 2 and len(two["threads"]["workers"]) == 2
    assert res["bytes"]["written_over_stored"] > 0.5
    table = bs.format_table(res)
    assert "occdata build, local disk" in table and "CPU kernel, s/sample" in table and "2/1" in table
    assert not list(tmp_path.glob("*.zarr"))  # every output removed after its run


def test_interleaved_rounds_pair_each_worker_count(synth_root: Path, tmp_path: Path) -> None:
    """--interleave: 1 worker, 2 workers, 1, 2 (a drifting host drifts within each pair)."""
    args = bs.parse_args(["--root", str(synth_root), "--gts", str(synth_root / "gts"), "--block-samples", "3",
                          "--lidar-sweeps", "0", "--sections", "build", "--workers", "1", "2", "--rounds", "2",
                          "--interleave"])
    res = bs.run_sections(args, bs.World.of(args.root, args.gts), tmp_path, lambda r: None)
    build = res["build"]
    one, two = build["workers_1"]["seconds_all"], build["workers_2"]["seconds_all"]
    assert len(one) == len(two) == 2
    assert build["paired_speedup_2_over_1"] == pytest.approx([one[0] / two[0], one[1] / two[1]])
    assert "2/1 within each round" in bs.format_table(res)
