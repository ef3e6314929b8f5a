"""benchmarks.bench_temporal plumbing (no timing asserts): the four models side by side, every figure
present, ratios to hist0 taken per round."""

from __future__ import annotations

from benchmarks import bench_temporal as bt


def test_bench_temporal_reports_every_model_runtime_and_the_training_step() -> None:
    res = bt.run("nano", (64, 176), channels=8, threads=1, runtimes=("torch",), rounds=1, repeats=1, warmup=1,
                 train_repeats=1)
    rows = res["inference"]["torch"]
    assert set(rows) == set(res["train"]) == {"hist0", "concat16", "cached16", "recurrent"}
    assert rows["hist0"]["ratio"] == rows["hist0"]["cpu_ratio"] == res["train"]["hist0"]["ratio"] == 1.0
    for v in rows.values():
        assert v["ms"] > 0 and v["cpu_ms"] > 0 and v["network_ms"] > 0 and v["frames_per_s"] > 0
    assert res["config"]["temporal_channels"] == 8 and res["config"]["input_hw"] == [64, 176]
    assert "cached16" in bt.format_report(res)
