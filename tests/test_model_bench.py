"""`fastocc bench` plumbing: the CLI parses into a BenchConfig and reports every stage (no timing asserts)."""

from __future__ import annotations

import json

from click.testing import CliRunner

from cli.fastocc_cli import main


def test_bench_cli_json_reports_stages_heads_and_ratio() -> None:
    result = CliRunner().invoke(
        main, ["bench", "--preset", "nano", "--head", "all", "--repeats", "1", "--warmup", "0", "--json"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert set(report["stages"]) == {"image", "view"}
    assert set(report["heads"]) == {"fastocc", "3dfcn", "deconv"}
    for stage in (*report["stages"].values(), *report["heads"].values()):
        assert stage["ms"] > 0 and stage["gmacs"] > 0 and stage["params"] > 0
    # the 3D FCN head costs more MACs than FastOcc's 2D head + interpolation on the same V_B
    assert report["heads"]["3dfcn"]["gmacs"] > report["heads"]["fastocc"]["gmacs"]
    assert report["fastocc_over_3dfcn_head_time"] > 0
    assert report["config"]["input_hw"] == [128, 352]


def test_bench_cli_rejects_cuda_without_gpu_in_one_line() -> None:
    import torch

    if torch.cuda.is_available():
        return
    result = CliRunner().invoke(main, ["bench", "--device", "cuda", "--repeats", "1"])
    assert result.exit_code == 1
    assert "CUDA is not available" in result.output


def test_bench_split_reports_2d_2dto3d_3d_per_preset_with_ratios_and_the_paper() -> None:
    """`fastocc bench --stage-split` (Table III): every stage of every preset, eager and ONNX Runtime, ratios to the
    first preset, the paper's tiny split beside ours. Tiny sizes here (plumbing, not figures)."""
    import pytest

    pytest.importorskip("onnxruntime")
    result = CliRunner().invoke(main, ["bench", "--stage-split", "--preset", "nano", "--preset", "tiny", "--input-hw",
                                       "64", "176", "--repeats", "1", "--warmup", "0", "--threads", "1", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert list(report["presets"]) == ["nano", "tiny"]
    for entry in report["presets"].values():
        assert entry["input_hw"] == [64, 176]
        for rt in ("torch", "onnx"):
            ms = entry[rt]
            assert set(ms) == {"2d", "2d_to_3d", "3d", "total"} and min(ms.values()) > 0
            assert abs(ms["total"] - ms["2d"] - ms["2d_to_3d"] - ms["3d"]) < 1e-6
    tiny = report["presets"]["tiny"]
    assert tiny["paper_ms"]["total"] == 62.80 and tiny["backbone_depth"] == 50
    assert report["presets"]["nano"]["torch_ratio_to_nano"]["total"] == 1.0
    nano_ms = report["presets"]["nano"]["torch"]
    for k, v in tiny["torch"].items():  # the ratio is a quotient of the measured times (no speed asserted here)
        assert tiny["torch_ratio_to_nano"][k] == pytest.approx(v / nano_ms[k])
    bad = CliRunner().invoke(main, ["bench", "--preset", "nano", "--preset", "tiny"])
    assert bad.exit_code == 2 and "--stage-split" in bad.output
