"""Scale figures for `occdata build` on Dask (issue 24), for docs/scale.md.

    python -m benchmarks.bench_scale --synth-samples 40 --write-samples 256 --json docs/bench_scale.json
    python -m benchmarks.bench_scale --root TREE --gts TREE/gts ...      # an existing nuScenes-format tree

1. build: samples/s with 1 worker (in this process) and 2 LocalCluster workers (start-up timed
   apart), peak RSS of each worker;
2. the write path alone: P writer processes (1, 2, 4), each writing its own blocks (random payloads
   of nuScenes-like sizes, the store's real layout and codecs) to local disk and to a local S3
   server (moto, a separate process on 127.0.0.1);
3. Dask's overhead per task: the round trip of an empty task against a block task's own time;
4. labels: `occdata labels --lidar-sweeps`, one task per scene, 1 and 2 workers (keyframes/s);
5. bytes written per sample against bytes stored per sample, for a build in this process (the
   process's `wchar` from /proc/self/io: every write, metadata and any staging included). Not a
   timing: `--bytes-only` runs this alone (seconds, on a small world).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import emit_json
from benchmarks.provenance import machine
from occdata.runtime.cluster import ClusterConfig, cluster_client, run_tasks
from occdata.store.build import BuildConfig, build_store
from occdata.store.create import create_arrays
from occdata.store.layout import FLAT_ARRAYS, PER_SAMPLE

__all__ = ["bench_build", "bench_bytes", "bench_labels", "bench_overhead", "bench_write"]

JPEG_BYTES_PER_SAMPLE = 6 * 160_000  # ~nuScenes: 6 JPEGs of 1600x900 at ~160 kB
UVD_ROWS_PER_SAMPLE = 20_000  # keyframe LiDAR points that land in a camera


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@dataclass(frozen=True)
class _Noop:
    """An empty task: what remains is the scheduler round trip."""

    units: int = 1

    def run(self, should_stop: Any) -> int:
        return 0


# --- 1. build ---------------------------------------------------------------------------------------
def bench_build(root: Path, gts: Path | None, block: int, tmp: Path) -> dict[str, Any]:
    """Each timed build follows an untimed one of the same tree (imports, numba caches, page cache
    warm in every process), so the figures are steady-state rates."""
    out: dict[str, Any] = {}
    build_store(BuildConfig(root=root, out=tmp / "warm1.zarr", gts=gts, block_samples=block, progress=False))
    t0 = time.perf_counter()
    r1 = build_store(BuildConfig(root=root, out=tmp / "w1.zarr", gts=gts, block_samples=block, progress=False))
    out["workers_1"] = {"seconds": time.perf_counter() - t0, "samples": r1.n_samples,
                        "samples_per_s": r1.n_samples / (time.perf_counter() - t0)}
    t0 = time.perf_counter()
    with cluster_client(ClusterConfig(workers=2)) as client:
        out["localcluster_2_startup_s"] = time.perf_counter() - t0
        build_store(BuildConfig(root=root, out=tmp / "warm2.zarr", gts=gts, block_samples=block,
                                cluster=ClusterConfig(workers=2),
                                progress=False), client=client)
        t1 = time.perf_counter()
        r2 = build_store(BuildConfig(root=root, out=tmp / "w2.zarr", gts=gts, block_samples=block,
                                cluster=ClusterConfig(workers=2),
                                     progress=False), client=client)
        dt = time.perf_counter() - t1
        out["workers_2"] = {"seconds": dt, "samples": r2.n_samples, "samples_per_s": r2.n_samples / dt}
        out["worker_peak_rss_mb"] = sorted(client.run(_peak_rss_mb).values())
        out["dask_overhead"] = bench_overhead(client)
    out["client_peak_rss_mb"] = _peak_rss_mb()
    out["speedup_2_over_1"] = out["workers_2"]["samples_per_s"] / out["workers_1"]["samples_per_s"]
    blocks = -(-r1.n_samples // block)
    out["block_task_s_1_worker"] = out["workers_1"]["seconds"] / blocks  # convert + commit of one block
    return out


def _bytes_written() -> int:
    """Bytes this process has passed to write(2) so far (Linux /proc/self/io `wchar`)."""
    with open("/proc/self/io") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("wchar:"))


def bench_bytes(root: Path, gts: Path | None, block: int, tmp: Path, lidar_sweeps: int = 0) -> dict[str, Any]:
    """Bytes written per sample / bytes stored per sample for one build in this process (1 worker:
    every write of the build is this process's). Goal (issue 33): 1.0x; with staging it was ~2x."""
    from occdata.store.sample import SampleOptions

    out_store = tmp / "bytes.zarr"
    before = _bytes_written()
    report = build_store(BuildConfig(root=root, out=out_store, gts=gts, block_samples=block, progress=False,
                                     options=SampleOptions(lidar_sweeps=lidar_sweeps)))
    written = _bytes_written() - before
    stored = sum(p.stat().st_size for p in out_store.rglob("*") if p.is_file())
    flat = sum(p.stat().st_size for name in ("images", "depth") for p in (out_store / name).rglob("*")
               if p.is_file())
    n = report.n_samples
    return {"samples": n, "lidar_sweeps": lidar_sweeps, "written_per_sample": written / n,
            "stored_per_sample": stored / n, "ragged_stored_per_sample": flat / n,
            "written_over_stored": written / stored}


def bench_labels(root: Path, tmp: Path) -> dict[str, Any]:
    """`occdata labels --lidar-sweeps` (one task per scene) with 1 worker (in this process) and 2
    LocalCluster workers; keyframes/s after an untimed warm-up run in every process."""
    from occdata.labels import LabelOptions, LabelsConfig, generate_labels

    def cfg(name: str) -> LabelsConfig:
        return LabelsConfig(root=root, out=tmp / name, options=LabelOptions(lidar_sweeps=True), progress=False)

    out: dict[str, Any] = {}
    generate_labels(cfg("lwarm1"))
    t0 = time.perf_counter()
    r1 = generate_labels(cfg("l1"))
    out["workers_1"] = {"seconds": time.perf_counter() - t0, "keyframes": r1.keyframes,
                        "keyframes_per_s": r1.keyframes / (time.perf_counter() - t0)}
    with cluster_client(ClusterConfig(workers=2)) as client:
        generate_labels(cfg("lwarm2"), client=client)
        t1 = time.perf_counter()
        r2 = generate_labels(cfg("l2"), client=client)
        dt = time.perf_counter() - t1
        out["workers_2"] = {"seconds": dt, "keyframes": r2.keyframes, "keyframes_per_s": r2.keyframes / dt}
        out["worker_peak_rss_mb"] = sorted(client.run(_peak_rss_mb).values())
    out["speedup_2_over_1"] = out["workers_2"]["keyframes_per_s"] / out["workers_1"]["keyframes_per_s"]
    return out


def bench_overhead(client: Any, n: int = 200) -> dict[str, float]:
    """Per-task cost of the scheduler round trips: empty tasks through run_tasks (window of 4)."""
    t0 = time.perf_counter()
    run_tasks(client, [_Noop() for _ in range(n)], desc="noop", progress=False, window=4)
    return {"tasks": n, "seconds_per_task": (time.perf_counter() - t0) / n}


# --- 2. the write path alone --------------------------------------------------------------------------
def _fake_rows(n: int, rng: np.random.Generator, tok_width: int) -> dict[str, np.ndarray]:
    rows = {}
    for s in PER_SAMPLE:
        shape = (n, *((s.shape[:-1] + (tok_width,)) if s.name.endswith("token") else s.shape))
        if s.name == "status/checksum":
            continue
        if s.sharded:  # labels: mostly one value, as real occupancy grids compress
            rows[s.name] = np.full(shape, 17, dtype=s.dtype)
            rows[s.name][:, 90:110, 90:110] = rng.integers(0, 17, (n, 20, 20, *shape[3:])).astype(s.dtype)
        else:
            rows[s.name] = rng.integers(0, 100, shape).astype(s.dtype)
    return rows


def _write_blocks(args: tuple[str, list[int], int, int, Any]) -> tuple[int, float, float]:
    """One writer process: whole blocks of fixed rows + its chunk-aligned flat regions. The payloads
    are made first; all writers start together (barrier). Returns (bytes, start, end) wall times."""
    import zarr

    from occdata.store.blocks import open_flat, open_for_task

    store, blocks, block, n, barrier = args
    rng = np.random.default_rng(blocks[0] if blocks else 0)
    todo = []
    for b in blocks:
        i0, i1 = b * block, min(n, (b + 1) * block)
        flat = {}
        for name, (row, dtype, chunk) in FLAT_ARRAYS.items():
            per = JPEG_BYTES_PER_SAMPLE if name == "images/jpeg" else UVD_ROWS_PER_SAMPLE
            rows = -(-(per * block) // chunk) * chunk
            if name == "images/jpeg":
                flat[name] = (b * rows, rng.integers(0, 255, rows, dtype=np.uint8))
            else:  # depth points: u, v in pixels, depth in metres (float32, as stored)
                flat[name] = (b * rows, (rng.random((rows, *row), dtype=np.float32) * [1600, 900, 60]).astype(dtype))
        todo.append((i0, i1, _fake_rows(i1 - i0, rng, 32), flat))
    root = open_for_task(store)
    barrier.wait()
    t0 = time.time()
    written = 0
    for i0, i1, fixed, flat in todo:
        for name, data in fixed.items():
            root[name][i0:i1] = data
        for name, (start, data) in flat.items():
            open_flat(store, name)[start : start + len(data)] = data
            written += data.nbytes
        zarr.open_array(store, path="status/state", mode="r+")[i0:i1] = 1
    return written, t0, time.time()


def _fresh_store(url: str, n: int, block: int) -> None:
    import zarr

    from occdata.store.build import consolidate

    root = zarr.open_group(url, mode="w")
    create_arrays(root, n, block, {"schema": "bench"}, 32)
    for name, (row, _, chunk) in FLAT_ARRAYS.items():
        per = JPEG_BYTES_PER_SAMPLE if name == "images/jpeg" else UVD_ROWS_PER_SAMPLE
        rows = -(-(per * block) // chunk) * chunk * (-(-n // block))
        root[name].resize((rows, *row))
    consolidate(url)


def bench_write(url_of: Any, n: int, block: int, writers: tuple[int, ...]) -> dict[str, Any]:
    out = {}
    ctx = mp.get_context("spawn")
    for p in writers:
        url = url_of(p)
        _fresh_store(url, n, block)
        blocks = list(range(-(-n // block)))
        with ctx.Manager() as manager, ctx.Pool(p) as pool:
            barrier = manager.Barrier(p)
            done = pool.map(_write_blocks, [(url, blocks[k::p], block, n, barrier) for k in range(p)])
        nbytes = sum(d[0] for d in done)
        dt = max(d[2] for d in done) - min(d[1] for d in done)
        out[f"writers_{p}"] = {"seconds": dt, "samples_per_s": n / dt, "MB_per_s": nbytes / dt / 1e6}
    return out


def _moto(port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(100):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return proc
        except OSError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("moto server did not start")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path)
    ap.add_argument("--gts", type=Path)
    ap.add_argument("--synth-samples", type=int, default=40, help="synthetic world size (2 scenes), if no --root")
    ap.add_argument("--block-samples", type=int, default=8)
    ap.add_argument("--write-samples", type=int, default=256)
    ap.add_argument("--writers", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--no-s3", action="store_true")
    ap.add_argument("--lidar-sweeps", type=int, default=0, help="for the bytes-written figure")
    ap.add_argument("--bytes-only", action="store_true", help="only the bytes written / stored figure")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_scale_"))
    try:
        root, gts = args.root, args.gts
        if root is None:
            from occdata.synth import SynthConfig, synthesize

            root = synthesize(SynthConfig(out=tmp / "world", scenes=2, samples=args.synth_samples // 2, progress=False))
            gts = root / "gts"
        result: dict[str, Any] = {
            "machine": machine(note="2-core VM shared with other developers: ratios within one run, noisy absolutes"),
            "bytes": bench_bytes(root, gts, args.block_samples, tmp, args.lidar_sweeps),
        }
        if args.bytes_only:
            emit_json(result, args.json)
            return
        result |= {
            "build": bench_build(root, gts, args.block_samples, tmp),
            "write_local": bench_write(lambda p: str(tmp / f"wr{p}.zarr"), args.write_samples, 32,
                                       tuple(args.writers)),
            "labels": bench_labels(root, tmp),
        }
        if not args.no_s3:
            port = 5000 + os.getpid() % 1000
            os.environ.update({"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "bench",
                               "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"})
            server = _moto(port)
            try:
                import fsspec

                fsspec.filesystem("s3").mkdir("bench")
                result["write_s3_moto"] = bench_write(lambda p: f"s3://bench/wr{p}.zarr", args.write_samples, 32,
                                                      tuple(args.writers))
            finally:
                server.kill()
                server.wait()
        emit_json(result, args.json)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
