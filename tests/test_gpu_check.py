"""benchmarks/gpu_check.py: every section reports (the dry path on the CPU), one failing section does not stop
the others, and the time budget skips what would start too late."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from benchmarks import gpu_check
from benchmarks.gpu_check import DRY_PLAN, GPU_PLAN, SECTIONS, CheckPlan, format_section, run_check

REPO = Path(__file__).resolve().parents[1]


def test_plans_cover_the_issue_list() -> None:
    """The CUDA plan: tiny and base, eager and compiled, fp32 and fp16/bf16, CUDA and TensorRT providers,
    50 training steps, nccl; the dry plan the same sections on CPU pieces."""
    assert GPU_PLAN.presets == ("tiny", "base") and GPU_PLAN.device == "cuda"
    assert "fp32" in GPU_PLAN.compile_dtypes and {"fp16", "bf16"} <= set(GPU_PLAN.dtypes)
    assert set(GPU_PLAN.providers) == {"CUDAExecutionProvider", "TensorrtExecutionProvider"}
    assert GPU_PLAN.train_steps == 50 and GPU_PLAN.dist_backend == "nccl"
    assert GPU_PLAN.budget_s < 8 * 60
    assert DRY_PLAN.device == "cpu" and DRY_PLAN.dist_backend == "gloo"
    assert DRY_PLAN.providers == ("CPUExecutionProvider",) and DRY_PLAN.compile_backend == "eager"
    assert list(SECTIONS) == ["env", "store", "train_amp", "loader", "dist", "onnx", "latency"]
    with pytest.raises(ValueError, match="dtypes"):
        dataclasses.replace(DRY_PLAN, dtypes=("fp8",))


def test_a_failing_section_is_reported_and_the_rest_run(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    calls: list[str] = []

    def ok(name: str):
        def fn(ctx):  # noqa: ANN001, ANN202
            calls.append(name)
            return {"figure": 1.5}
        return fn

    def boom(ctx):  # noqa: ANN001, ANN202
        calls.append("b")
        raise RuntimeError("NCCL error: unhandled system error\nsecond line")

    monkeypatch.setattr(gpu_check, "SECTIONS", {"a": ok("a"), "b": boom, "c": ok("c")})
    lines: list[str] = []
    out = tmp_path / "r.json"
    result = run_check(DRY_PLAN, say=lines.append, json_path=str(out))
    assert calls == ["a", "b", "c"]
    s = result["sections"]
    assert s["a"]["status"] == "ok" and s["a"]["figure"] == 1.5 and s["c"]["status"] == "ok"
    assert s["b"] == {"status": "error", "error": "RuntimeError: NCCL error: unhandled system error",
                      "seconds": s["b"]["seconds"]}
    assert lines[1].startswith("[b] error (") and "\n" not in lines[1]
    assert json.loads(out.read_text())["sections"].keys() == {"a", "b", "c"}


def test_time_budget_skips_later_sections(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = iter(float(t) for t in range(0, 1000, 10))  # each perf_counter call: 10 s later
    monkeypatch.setattr(gpu_check, "time", SimpleNamespace(perf_counter=lambda: next(clock)))
    monkeypatch.setattr(gpu_check, "SECTIONS", {k: (lambda ctx: {}) for k in ("a", "b", "c", "d")})
    plan: CheckPlan = dataclasses.replace(DRY_PLAN, budget_s=25.0)
    result = run_check(plan, say=lambda _: None)
    status = {k: v["status"] for k, v in result["sections"].items()}
    # t0 = 0; "a" starts at 10 (ok), "b" at 40 > 25: skipped, and so on
    assert status == {"a": "ok", "b": "skipped", "c": "skipped", "d": "skipped"}
    assert "time budget 25 s spent" in result["sections"]["d"]["reason"]


def test_format_section_one_line() -> None:
    line = format_section("loader", {"status": "ok", "seconds": 2.04, "workers": {"2": {"samples_per_s": 12.345}}})
    assert line == "[loader] ok (2.0 s): workers {2: {samples_per_s: 12.3}}"


def test_dry_run_every_section_reports(tmp_path: Path) -> None:
    """The script as documented, on the CPU: every section ok with its figures (about 40 s of CPU)."""
    out = tmp_path / "dry.json"
    proc = subprocess.run(["bash", str(REPO / "scripts" / "gpu_check.sh"), "--dry-run", "--json", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())
    sections = result["sections"]
    assert list(sections) == list(SECTIONS)
    bad = {k: v.get("error", v.get("reason")) for k, v in sections.items() if v["status"] != "ok"}
    assert not bad, bad
    for name in SECTIONS:
        assert f"[{name}] ok (" in proc.stdout
    train = sections["train_amp"]
    assert train["opt_steps"] == DRY_PLAN.train_steps and math.isfinite(train["last_loss"])
    assert sections["loader"]["loader_over_step"]["1"] > 0
    assert sections["dist"]["backend"] == "gloo" and sections["dist"]["world_size"] == 1
    nano = sections["latency"]["presets"]["nano"]
    assert all(nano[f"eager_{d}_ms"] > 0 for d in DRY_PLAN.dtypes) and nano["compiled_fp32_ms"] > 0
    assert sections["onnx"]["providers"]["CPUExecutionProvider"]["active"] == "CPUExecutionProvider"


def test_one_failing_measurement_keeps_the_others() -> None:
    rows: dict = {}
    gpu_check._measure(rows, "eager_fp16_ms", lambda: 1 / 0)
    gpu_check._measure(rows, "eager_fp32_ms", lambda: 12.5)
    assert rows == {"eager_fp16_ms": "error: ZeroDivisionError: division by zero", "eager_fp32_ms": 12.5}
