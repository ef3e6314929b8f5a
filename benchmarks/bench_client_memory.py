"""Peak memory of the `occdata build` and `labels` clients against the number of samples (issue 48).

    python -m benchmarks.bench_client_memory --sizes 3400 10200 34000 --plan-only 34000 --commands build labels \\
        plan --code before=/path/to/older/checkout --code after=. --json docs/results/bench_client_memory.json

Trees replay the real keyframe (`tests/replicated_tree.py`: 2 scenes, the real sensor files linked,
the real Occ3D label linked per sample), made once under `--trees`. Each (code, size, command) runs in
a fresh process with that checkout first on PYTHONPATH and one worker, i.e. in that process, with the
task's work replaced by a no-op: what is measured is the client alone (tables, plan, the store's
creation, every task made and handed over, the final commit), the part that a cluster's workers do
not share. A build task returns at once what a converted block would (`BlockSummary`, nothing
written); a labels task returns no counts. So the figures are the client's whatever the conversion
costs, and 34,000 samples take a minute, not hours.

`--plan-only N` measures the trees of N samples with `plan` alone: the tables read and checked
(`read_inputs`) and the payload plan (`payload_bounds`, `plan_regions`), without the store or tasks.

Figures per run: `peak_rss_mib` (VmHWM at the end), `wall_s`, `cpu_s` (this process), and per size
pair the slope in KiB per sample. `--trace` (slower: tracemalloc) adds, for the build, the Python
objects alive right after the tables are read and at the end of `read_inputs`, and the traced peak, by
source line. RSS is the figure to trust; wall times on a shared 2-core VM are noisy.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["child", "measure"]

_REPO = Path(__file__).resolve().parents[1]


def _vm_hwm_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


# --- the child: one command in a fresh process (runs with --code's occdata) ---------------------------------


def _top(snapshot: Any, n: int = 6) -> dict[str, Any]:
    stats = snapshot.statistics("lineno")
    return {"traced_mib": round(sum(s.size for s in stats) / 2**20, 1),
            "top": [{"where": f"{Path(s.traceback[0].filename).name}:{s.traceback[0].lineno}",
                     "mib": round(s.size / 2**20, 1), "objects": s.count} for s in stats[:n]]}


def _trace_tables(found: dict[str, Any]) -> None:
    """Note the live Python objects right after `read_tables` returns (the rows kept, before records)."""
    import tracemalloc

    import occdata.nuscenes.reader as reader

    original = reader.read_tables

    def traced(*args: Any, **kwargs: Any) -> Any:
        idx = original(*args, **kwargs)
        found["after_tables"] = _top(tracemalloc.take_snapshot())
        return idx

    reader.read_tables = traced


def _no_op_build() -> None:
    """Build tasks that convert nothing: the summary of a placed block with no errors."""
    import occdata.store.blocks as blocks
    from occdata.store.layout import FLAT_ARRAYS

    blocks.convert_block = lambda job: blocks.BlockSummary(job.block, (), (0,) * len(FLAT_ARRAYS))


def _no_op_labels() -> None:
    import occdata.labels.generate as generate

    generate.SceneJob.run = lambda self, should_stop=None: {}


def child(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one command's client on `spec["root"]`; its peak RSS and wall time (and traced objects)."""
    import gc
    import tracemalloc

    root, out = Path(spec["root"]), Path(spec["out"])
    found: dict[str, Any] = {}
    if spec.get("trace"):
        tracemalloc.start(1)
        _trace_tables(found)
    t0, c0 = time.perf_counter(), time.process_time()
    if spec["command"] == "build":
        _no_op_build()
        from occdata.store.build import BuildConfig, build_store

        config = BuildConfig(root=root, out=out, gts=root / "gts", progress=False)
        if spec.get("trace"):
            from occdata.store.inputs import read_inputs

            inputs = read_inputs(config)
            gc.collect()
            found["after_inputs"] = _top(tracemalloc.take_snapshot())
            found["traced_peak_mib"] = round(tracemalloc.get_traced_memory()[1] / 2**20, 1)
            found["samples"] = len(inputs.ds.samples)
            del inputs
        build_store(config)
    elif spec["command"] == "plan":  # the tables and the plan alone: read_inputs, payload_bounds, plan_regions
        from occdata.store.build import BuildConfig
        from occdata.store.inputs import read_inputs
        from occdata.store.plan import block_spans, payload_bounds, plan_regions

        config = BuildConfig(root=root, out=out, gts=root / "gts", progress=False)
        inputs = read_inputs(config)
        plan_regions(payload_bounds(inputs.ds.samples, inputs.histories, config.options),
                     block_spans(len(inputs.ds.samples), config.block_samples))
    else:
        _no_op_labels()
        from occdata.labels import LabelOptions, LabelsConfig, generate_labels

        generate_labels(LabelsConfig(root=root, out=out, progress=False, options=LabelOptions()))
    return {"wall_s": round(time.perf_counter() - t0, 2), "cpu_s": round(time.process_time() - c0, 2),
            "peak_rss_mib": round(_vm_hwm_mib(), 1), **found}


# --- the parent ----------------------------------------------------------------------------------------------


def measure(code: Path, spec: dict[str, Any]) -> dict[str, Any]:
    """`child(spec)` in a fresh process with `code` first on PYTHONPATH."""
    env = {**os.environ, "PYTHONPATH": str(code), "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)], env=env,
                          capture_output=True, text=True, cwd=code)
    if proc.returncode != 0:
        raise SystemExit(f"{spec['command']} on {spec['root']} with {code} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _tree(trees: Path, n: int, scene_samples: int = 0, boxes: int = 0, other_rows: int = 0) -> Path:
    """The replayed tree of `n` samples (2 scenes, or scenes of `scene_samples`; `boxes` tracked boxes
    per scene, one annotation each per sample; `other_rows` sample_data rows a sample that no command
    keeps), made once."""
    from benchmarks.common import SHARED_DATA
    from tests.replicated_tree import make_replicated_tree

    root = trees / (f"replay{n}" + (f"_s{scene_samples}" if scene_samples else "") + (f"_b{boxes}" if boxes else "")
                    + (f"_o{other_rows}" if other_rows else ""))
    if not (root / "v1.0-mini" / "scene.json").is_file():
        shutil.rmtree(root, ignore_errors=True)
        label = next((SHARED_DATA / "occ3d-label").glob("*/labels.npz"))
        per = scene_samples or n // 2
        make_replicated_tree(SHARED_DATA / "nuscenes-real", label, root, n // per, per, boxes=boxes,
                              other_rows=other_rows)
    return root


def _slopes(runs: dict[str, Any], sizes: list[int]) -> dict[str, float]:
    """KiB per sample between consecutive sizes, from the peak RSS."""
    out = {}
    for a, b in zip(sizes, sizes[1:], strict=False):
        if str(a) in runs and str(b) in runs:
            ra, rb = runs[str(a)]["peak_rss_mib"], runs[str(b)]["peak_rss_mib"]
            out[f"{a}->{b}"] = round((rb - ra) * 1024 / (b - a), 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[3400, 10200, 34000], help="samples per tree")
    ap.add_argument("--code", action="append", default=[], metavar="NAME=DIR",
                    help="a checkout to measure (repeatable; default: this one as 'after')")
    ap.add_argument("--commands", nargs="+", default=["build", "labels"], help="of build, labels, plan")
    ap.add_argument("--plan-only", type=int, nargs="*", default=[], metavar="N",
                    help="sizes measured with `plan` alone (the tables and the plan: large trees, little time)")
    ap.add_argument("--trace", type=int, nargs="*", default=[], metavar="N",
                    help="also trace the build's Python objects at these sizes (tracemalloc, slower)")
    ap.add_argument("--trees", type=Path, help="keep the trees here (reused when present)")
    ap.add_argument("--scene-samples", type=int, default=0, metavar="K",
                    help="scenes of K samples (nuScenes: ~40) instead of 2 scenes of n/2 (a labels task holds a scene)")
    ap.add_argument("--boxes", type=int, default=0, metavar="B",
                    help="B tracked boxes per scene, one annotation each per sample (nuScenes: ~34 a keyframe)")
    ap.add_argument("--other-rows", type=int, default=0, metavar="R",
                    help="R more sample_data rows (and ego poses) a sample that no command keeps (nuScenes: ~70)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return
    sys.path.insert(0, str(_REPO))
    from benchmarks.common import emit_json
    from benchmarks.provenance import finish, git_state, machine

    codes = dict(c.split("=", 1) for c in args.code) or {"after": str(_REPO)}
    codes = {name: Path(d).resolve() for name, d in codes.items()}
    record = machine(codes={n: {"dir": str(d), "commit": git_state(d)[0], "dirty": git_state(d)[1]}
                            for n, d in codes.items()},
                     note="client only: one worker (this process), tasks replaced by no-ops; a 2-core VM "
                          "shared with other jobs: RSS is the figure, timings are noisy")
    work = Path(tempfile.mkdtemp(prefix="bench_client_memory_"))
    trees = args.trees or work / "trees"
    commands = args.commands + (["plan"] if args.plan_only and "plan" not in args.commands else [])
    runs: dict[str, Any] = {name: {c: {} for c in commands} for name in codes}
    try:
        for n in args.sizes:
            root = _tree(trees, n, args.scene_samples, args.boxes, args.other_rows)
            for command in ["plan"] if n in args.plan_only else args.commands:
                for name, code in codes.items():
                    out = work / f"{name}_{command}_{n}" / ("data.zarr" if command == "build" else "")
                    spec = {"command": command, "root": str(root), "out": str(out),
                            "trace": command == "build" and n in args.trace}
                    runs[name][command][str(n)] = measure(code, spec)
                    print(name, command, n, runs[name][command][str(n)], file=sys.stderr)
                    shutil.rmtree(work / f"{name}_{command}_{n}", ignore_errors=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    slopes = {name: {c: _slopes(r, args.sizes) for c, r in per.items()} for name, per in runs.items()}
    emit_json({"machine": finish(record), "sizes": args.sizes, "scene_samples": args.scene_samples or "n/2",
               "boxes_per_scene": args.boxes,
               "other_rows_per_sample": args.other_rows, "runs": runs, "kib_per_sample": slopes}, args.json)


if __name__ == "__main__":
    main()
