"""Memory and start-up of `occdata build`, `labels` and `scan` against the size of the tables.

    python -m benchmarks.bench_reader_memory --json docs/results/bench_reader_memory.json
    python -m benchmarks.bench_reader_memory --code /path/to/older/checkout --json before.json  # the same on older code

Two trees that differ only in their tables: the same `--real-scenes` rendered scenes (train/val), plus
table-only scenes (`occdata synth --table-only-scenes`, 40 keyframes each, no sensor files) up to 10
and to 850 scenes in all (nuScenes trainval: 850 scenes, 34,149 keyframes). `build` and `labels` select
the rendered scenes (`--split train --split val`), so every run does the same tasks and only the
tables grow. Each command runs in a fresh process on a LocalCluster of 2 workers with 1 thread each
(`scan` has no workers); the figures:

- `client_peak_rss_mib`: the command's process (VmHWM of /proc/self/status at its end);
- `worker_peak_rss_mib`: each Dask worker's VmHWM at the end of the run (not the nanny);
- `startup_s`: from calling the command's function (the cluster already up) to the first task
  computing on a worker (Dask's task stream); `first_task_done_s` to the first task's end: a task that
  reads the tables itself shows there, not in `startup_s`;
- `wall_s`: the whole call.

`--code DIR` runs the commands with `DIR` first on PYTHONPATH (e.g. a checkout of an older commit): the
trees are written once by this checkout. RSS is the main figure; timings on a shared 2-core VM are noisy.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["make_tree", "measure"]

_REPO = Path(__file__).resolve().parents[1]
SPLITS = ("train", "val")


def _vm_hwm_mib() -> float:
    """This process's peak resident set (VmHWM), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def make_tree(out: Path, real: int, scenes: int, samples: int, width: int, height: int) -> Path:
    """`real` rendered scenes of `samples` keyframes, then table-only scenes (40 keyframes) up to `scenes`."""
    from occdata.synth import SynthConfig, synthesize

    return synthesize(SynthConfig(out=out, scenes=real, samples=samples, seed=7, width=width, height=height,
                                  progress=False, table_only_scenes=scenes - real))


# --- the child: one command in a fresh process (runs with --code's occdata) ---------------------------------


def _run_command(spec: dict[str, Any], client: Any) -> None:
    root, out = Path(spec["root"]), Path(spec["out"])
    if spec["command"] == "build":
        from occdata.store.build import BuildConfig, build_store
        from occdata.store.sample import SampleOptions

        build_store(BuildConfig(root=root, out=out, gts=root / "gts", splits=SPLITS, progress=False,
                                options=SampleOptions(lidar_sweeps=spec["sweeps"])), client=client)
    elif spec["command"] == "labels":
        from occdata.labels import LabelOptions, LabelsConfig, generate_labels

        generate_labels(LabelsConfig(root=root, out=out, splits=SPLITS, progress=False,
                                     options=LabelOptions(all_sweeps=True)), client)
    else:
        from occdata.nuscenes.summary import scan_tree

        scan_tree(root, None, check_files=False)


def _child(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one command; its client and worker peaks and timings."""
    if spec["command"] == "scan":
        t0 = time.perf_counter()
        _run_command(spec, None)
        return {"wall_s": round(time.perf_counter() - t0, 2), "client_peak_rss_mib": round(_vm_hwm_mib(), 1)}
    from distributed import get_task_stream

    from occdata.runtime.cluster import ClusterConfig, cluster_client

    with cluster_client(ClusterConfig(workers=2)) as client:
        client.run(lambda: None)  # the workers are up before the clock starts
        t0_wall, t0 = time.time(), time.perf_counter()
        with get_task_stream(client=client) as stream:
            _run_command(spec, client)
        wall = time.perf_counter() - t0
        computes = [ss for rec in stream.data for ss in rec["startstops"] if ss["action"] == "compute"]
        workers = client.run(_vm_hwm_mib)
    return {
        "wall_s": round(wall, 2),
        "startup_s": round(min(ss["start"] for ss in computes) - t0_wall, 2),
        "first_task_done_s": round(min(ss["stop"] for ss in computes) - t0_wall, 2),
        "tasks": len(computes),
        "client_peak_rss_mib": round(_vm_hwm_mib(), 1),
        "worker_peak_rss_mib": sorted(round(v, 1) for v in workers.values()),
    }


# --- the parent ----------------------------------------------------------------------------------------------


def measure(code: Path, command: str, root: Path, out: Path, sweeps: int) -> dict[str, Any]:
    """Run `command` on `root` in a fresh process with `code` first on PYTHONPATH."""
    spec = {"command": command, "root": str(root), "out": str(out), "sweeps": sweeps}
    env = {**os.environ, "PYTHONPATH": str(code), "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)], env=env,
                          capture_output=True, text=True, cwd=code)
    if proc.returncode != 0:
        raise SystemExit(f"{command} on {root} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--code", type=Path, default=_REPO, help="checkout whose occdata runs the commands")
    ap.add_argument("--scenes", type=int, nargs="+", default=[10, 850], help="scenes in the tables")
    ap.add_argument("--real-scenes", type=int, default=2, help="rendered scenes (the ones built and labelled)")
    ap.add_argument("--samples", type=int, default=4, help="keyframes per rendered scene")
    ap.add_argument("--sweeps", type=int, default=9, help="build --lidar-sweeps N (labels always use --all-sweeps)")
    ap.add_argument("--commands", nargs="+", default=["build", "labels", "scan"])
    ap.add_argument("--trees", type=Path, help="keep the trees here (reused when present)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(json.loads(args.child))))
        return
    sys.path.insert(0, str(_REPO))
    from benchmarks.common import emit_json
    from benchmarks.provenance import finish, git_state, machine

    code = args.code.resolve()
    record = machine(code=str(code), code_commit=git_state(code)[0], workers=2, threads_per_worker=1,
                     real_scenes=args.real_scenes, samples=args.samples, build_lidar_sweeps=args.sweeps,
                     note="2-core VM shared with other jobs: RSS is the main figure, timings are noisy")
    base = Path(tempfile.mkdtemp(prefix="bench_reader_memory_"))
    trees = args.trees or base / "trees"
    runs: dict[str, Any] = {}
    for n in args.scenes:
        root = trees / f"scenes{n}"
        if not (root / "v1.0-mini" / "scene.json").is_file():
            make_tree(root, args.real_scenes, n, args.samples, 320, 180)
        table_mib = sum(p.stat().st_size for p in (root / "v1.0-mini").glob("*.json")) / 2**20
        runs[str(n)] = {"tables_mib": round(table_mib, 1)}
        for command in args.commands:
            out = base / f"{command}{n}" / ("data.zarr" if command == "build" else "")
            runs[str(n)][command] = measure(code, command, root, out, args.sweeps)
            print(n, command, runs[str(n)][command], file=sys.stderr)
    emit_json({"machine": finish(record), "runs": runs}, args.json)


if __name__ == "__main__":
    main()
