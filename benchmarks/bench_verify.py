"""`occdata verify` in one process against a 2-worker LocalCluster (issue 48, deliverable 4).

    python -m benchmarks.bench_verify --root TREE --gts TREE/gts --json docs/results/bench_verify.json
    python -m benchmarks.bench_verify --store data.zarr --json out.json     # an existing store

Builds the store of `--root` once (one process, `--block-samples`), unless `--store` names one, then
runs `verify_store` in this process (1 worker) and on a LocalCluster of 2 single-threaded workers,
each timed run after an untimed warm one, through benchmarks/scale_meter.py: samples/s, CPU seconds
per sample (client plus workers), the ratio 2/1 of both. One thread per process (the thread
variables are set before the libraries load). A shared 2-core VM: the CPU ratio is the steadier figure.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

for _name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

__all__ = ["bench_verify"]


def bench_verify(store: Path, workers: tuple[int, ...] = (1, 2)) -> dict[str, Any]:
    """Verify `store` at each worker count (1: in this process): scale_meter's figures, and the ratios."""
    from benchmarks.scale_meter import measure
    from occdata.runtime.cluster import ClusterConfig, cluster_client
    from occdata.store.commands.verify import verify_store
    from occdata.store.reader import open_store

    out: dict[str, Any] = {}
    for w in workers:
        with cluster_client(ClusterConfig(workers=w)) as client:
            def run(client: Any = client) -> int:
                reader = open_store(store)
                problems = verify_store(reader, client=client)
                if problems:
                    raise SystemExit(f"verify found {len(problems)} problems in {store}: {problems[0]}")
                return reader.n_samples

            run()  # warm: imports, page cache
            out[f"workers_{w}"] = measure(run, client)
    one = out.get("workers_1")
    for w in (w for w in workers if w != 1 and one is not None):
        rec = out[f"workers_{w}"]
        out[f"speedup_{w}_over_1"] = rec["units_per_s"] / one["units_per_s"]
        out[f"cpu_{w}_over_1"] = sum(rec["cpu_s_per_unit"].values()) / sum(one["cpu_s_per_unit"].values())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, help="a nuScenes-format tree to build first")
    ap.add_argument("--gts", type=Path)
    ap.add_argument("--store", type=Path, help="an existing store (no build)")
    ap.add_argument("--block-samples", type=int, default=32)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from benchmarks.common import emit_json
    from benchmarks.provenance import finish, machine

    record = machine(threads_per_process=1, note="2-core VM shared with other jobs: timings are noisy")
    with tempfile.TemporaryDirectory(prefix="bench_verify_") as tmp:
        store = args.store
        if store is None:
            if args.root is None:
                ap.error("give --root (a tree to build) or --store")
            from occdata.store.build import BuildConfig, build_store

            store = Path(tmp) / "data.zarr"
            build_store(BuildConfig(root=args.root, out=store, gts=args.gts, block_samples=args.block_samples,
                                    progress=False))
        res = bench_verify(store)
    for w in ("1", "2"):
        rec = res[f"workers_{w}"]
        print(f"{w} worker(s): {rec['units_per_s']:.1f} samples/s, "
              f"{sum(rec['cpu_s_per_unit'].values()) * 1e3:.1f} CPU-ms/sample", file=sys.stderr)
    emit_json({"machine": finish(record), "store": str(args.store or args.root), "verify": res}, args.json)


if __name__ == "__main__":
    main()
