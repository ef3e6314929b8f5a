"""What an idle 2-worker LocalCluster costs in CPU, per second of wall time (issue 48, deliverable 5).

    python -m benchmarks.bench_dask_idle --seconds 20 --json docs/results/bench_dask_idle.json

The cluster of `occdata build --workers 2` (`occdata.runtime.cluster.cluster_client`), started, left
3 s, then `--seconds` with no task: the CPU of this process (scheduler, nannies, client) and of each
worker over that time, in cores (CPU seconds per wall second), under Dask settings that differ from
ours one at a time (`VARIANTS`). A cost paid per second of wall time is paid per sample in
proportion to how long a sample takes: on a loaded machine, where a run is several times longer, it
is several times larger per sample. Each variant in a fresh process. The 2-core VM is shared with
other jobs: small figures are noisy.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["VARIANTS", "idle_cost"]

_REPO = Path(__file__).resolve().parents[1]
VARIANTS: dict[str, dict[str, Any]] = {
    "ours": {},
    "with Dask's profiler (the default)": {"distributed.worker.profile.enabled": True},
    "no work stealing, monitors at 1 s / 5 s": {"distributed.scheduler.work-stealing": False,
                                                 "distributed.worker.memory.monitor-interval": "1s",
                                                 "distributed.admin.system-monitor.interval": "5s"},
}


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def idle_cost(extra: dict[str, Any], seconds: float) -> dict[str, Any]:
    """Cores used by this process and each worker of an idle 2-worker cluster, with `extra` Dask config."""
    import dask

    from occdata.runtime.cluster import ClusterConfig, cluster_client

    with dask.config.set(extra), cluster_client(ClusterConfig(workers=2)) as client:
        time.sleep(3)
        w0, c0, t0 = client.run(_cpu), _cpu(), time.perf_counter()
        time.sleep(seconds)
        w1, c1, wall = client.run(_cpu), _cpu(), time.perf_counter() - t0
    return {"config": extra, "wall_s": round(wall, 2), "client_cores": round((c1 - c0) / wall, 4),
            "worker_cores": sorted(round((w1[a] - w0[a]) / wall, 4) for a in w1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(idle_cost(json.loads(args.child), args.seconds)))
        return
    sys.path.insert(0, str(_REPO))
    from benchmarks.common import emit_json
    from benchmarks.provenance import finish, machine

    record = machine(note="2-core VM shared with other jobs: small figures are noisy")
    out = {}
    for name, extra in VARIANTS.items():
        proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_dask_idle", "--seconds", str(args.seconds),
                               "--child", json.dumps(extra)], cwd=_REPO, capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": str(_REPO)}, check=True)
        out[name] = json.loads(proc.stdout.strip().splitlines()[-1])
        print(name, out[name], file=sys.stderr)
    emit_json({"machine": finish(record), "variants": out}, args.json)


if __name__ == "__main__":
    main()
