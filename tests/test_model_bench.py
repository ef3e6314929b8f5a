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
