"""Scale figures for `occdata build` and `occdata labels` on Dask, for docs/scale.md.

The 240-keyframe table of docs/scale.md (alone on the machine; ~25 min on the project's 2-core VM, plus
~5-8 min to make the world once, `occdata synth --scenes 6 --samples 40 --seed 91`: 240 keyframes at
1600x900, ~9 GB mostly depth maps, kept in `--world` for a rerun; plus ~5 min for `--profile`'s
profiled builds):

    python -m benchmarks.bench_scale --world /tmp/bench_scale_world --synth-scenes 6 --synth-samples 240 \\
        --synth-seed 91 --block-samples 24 --lidar-sweeps 9 --rounds 2 --profile /tmp/bench_scale_profile \\
        --json docs/results/bench_scale_240kf.json

    python -m benchmarks.bench_scale --root TREE --gts TREE/gts ...  # an existing nuScenes-format tree
    python -m benchmarks.bench_scale --bytes-only --synth-samples 8 --block-samples 4 --lidar-sweeps 2

Every figure at 1 worker (in this process, as `occdata build --workers 1` runs) and 2 (a LocalCluster
of 2 single-threaded workers, started once per section, start-up timed apart), one thread per
process (`--threads 1`: NUMBA/OMP/MKL/OPENBLAS_NUM_THREADS, OpenCV; the script re-executes itself
once with them set). Each timed run follows an untimed warm one in the same processes (imports,
numba caches, page cache); `--rounds N` times N runs and keeps the fastest (all are in the JSON).
Per run (benchmarks/scale_meter.py): samples/s; CPU seconds per sample, user and kernel, client plus
workers, the kernel's share and the client's share; cores busy; context switches; bytes written
against bytes stored per sample; the time from the start to the first task running; the workers'
busy share. Sections (`--sections`):

1. bytes: bytes written per sample against bytes stored per sample, one build in this process (its
   `wchar` from /proc/self/io: every write, metadata included). `--bytes-only` runs this alone;
2. build: `occdata build --lidar-sweeps N` to local disk, 1 and 2 workers, the ratio 2/1 and its
   ceiling from the block granularity (blocks of `--block-samples`, one task each); Dask's round
   trip per empty task, peak RSS per worker;
3. s3: the same build to a local S3 server (moto, a separate process on 127.0.0.1, its CPU counted
   apart);
4. labels: `occdata labels --all-sweeps` (one task per scene), 1 and 2 workers (keyframes/s; the
   warm run labels one scene per worker);
5. write: the write path alone, P writer processes (`--writers`), each writing its own blocks
   (random payloads of nuScenes-like sizes, the store's layout and codecs) to local disk and (unless
   `--no-s3`) to the S3 server;
6. profile (`--profile DIR`): the CLI build under strace / perf / py-spy, whichever are installed
   (benchmarks/scale_profile.py), for where the threads wait. Not timed figures. On the project's VM
   strace and perf are installed, py-spy is not (`pip install py-spy` adds it; `--help` lists what
   is found).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import multiprocessing as mp
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks.common import emit_json, wait_for_port, write_json
from benchmarks.provenance import REPO, finish, machine
from benchmarks.scale_meter import measure
from benchmarks.scale_profile import PROFILERS as PROFILE_TOOLS
from benchmarks.scale_profile import available_profilers, profile_builds
from occdata.runtime.cluster import ClusterConfig, cluster_client, run_tasks
from occdata.store.build import BuildConfig, build_store
from occdata.store.create import create_arrays
from occdata.store.layout import FLAT_ARRAYS, PER_SAMPLE

__all__ = ["World", "bench_build", "bench_bytes", "bench_labels", "bench_overhead", "bench_write", "block_ceiling",
           "format_table", "run_sections"]

JPEG_BYTES_PER_SAMPLE = 6 * 160_000  # ~nuScenes: 6 JPEGs of 1600x900 at ~160 kB
UVD_ROWS_PER_SAMPLE = 20_000  # keyframe LiDAR points that land in a camera
SECTIONS = ("bytes", "build", "s3", "labels", "write")
THREAD_ENV = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _log(msg: str) -> None:
    print(f"[bench_scale {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class _Noop:
    """An empty task: what remains is the scheduler round trip."""

    units: int = 1

    def run(self, should_stop: Any) -> int:
        return 0


@dataclass(frozen=True)
class World:
    """The input tree: its root, labels folder, scenes (name, keyframes) and image size."""

    root: Path
    gts: Path | None
    scenes: tuple[tuple[str, int], ...]
    image_size: tuple[int, int]

    @property
    def samples(self) -> int:
        return sum(n for _, n in self.scenes)

    @staticmethod
    def of(root: Path, gts: Path | None) -> World:
        version = next(p.parent for p in sorted(root.glob("v1.0-*/scene.json")))
        scenes = tuple((s["name"], int(s["nbr_samples"])) for s in json.loads((version / "scene.json").read_text()))
        jpeg = next(root.glob("samples/CAM_FRONT/*.jpg"), None)
        image = cv2.imread(str(jpeg)) if jpeg is not None else None
        return World(root, gts, scenes, (image.shape[1], image.shape[0]) if image is not None else (0, 0))


def make_world(args: argparse.Namespace, tmp: Path) -> World:
    """--root as given, else the synthetic world in --world (made there once) or in `tmp`, by
    `occdata synth` with the libraries' default threads (not timed)."""
    if args.root is not None:
        return World.of(args.root, args.gts)
    root = args.world or tmp / "world"
    if any(root.glob("v1.0-*/scene.json")):
        world = World.of(root, root / "gts")
        if (world.samples, len(world.scenes)) != (args.synth_samples, args.synth_scenes):
            _log(f"warning: {root} holds {len(world.scenes)} scenes, {world.samples} keyframes (kept as it is)")
        return world
    per_scene = args.synth_samples // args.synth_scenes
    _log(f"synthesising {args.synth_scenes} scenes x {per_scene} keyframes (seed {args.synth_seed}) in {root}")
    env = {k: v for k, v in os.environ.items() if k not in THREAD_ENV}
    subprocess.run([sys.executable, "-m", "cli.occdata_cli", "synth", "--out", str(root), "--scenes",
                    str(args.synth_scenes), "--samples", str(per_scene), "--seed", str(args.synth_seed),
                    "--no-progress"], cwd=REPO, env=env | {"PYTHONPATH": str(REPO)}, check=True,
                   stdout=subprocess.DEVNULL)
    return World.of(root, root / "gts")


def block_ceiling(sizes: Sequence[int], workers: int) -> float:
    """The best speed-up over one worker when each item of `sizes` is one task, handed out in order to
    the least loaded worker (as Dask does): total / the largest worker's load."""
    loads = [0] * workers
    for s in sizes:
        loads[loads.index(min(loads))] += s
    return sum(sizes) / max(loads)


# --- runs to scale ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    """A kind of run to scale. `run(tag, client, workers)` does it into output `tag` and returns its
    units; `warm` (default `run`) is the untimed warm-up; `out(tag)` is the output's location."""

    name: str
    run: Callable[[str, Any, int], int]
    out: Callable[[str], Path | str]
    warm: Callable[[str, Any, int], int] | None = None


def _stored_bytes(out: Path | str) -> int | None:
    """Bytes of a local output (None for a URL: the client's wchar does not count socket sends)."""
    if isinstance(out, str) and "://" in out:
        return None
    return sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file())


def _drop(out: Path | str) -> None:
    if isinstance(out, str) and "://" in out:
        import fsspec

        fs, path = fsspec.core.url_to_fs(out)
        fs.invalidate_cache()
        with contextlib.suppress(FileNotFoundError):
            fs.rm(path, recursive=True)
    else:
        shutil.rmtree(out, ignore_errors=True)


def build_job(world: World, base: Path | str, lidar_sweeps: int, block: int, name: str = "build") -> Job:
    """`occdata build --lidar-sweeps N` into `base/<tag>.zarr` (a folder or an s3:// URL)."""
    from occdata.store.sample import SampleOptions

    def out(tag: str) -> Path | str:
        return f"{base}/{tag}.zarr" if isinstance(base, str) else base / f"{tag}.zarr"

    def run(tag: str, client: Any, workers: int) -> int:
        cfg = BuildConfig(root=world.root, out=out(tag), gts=world.gts, block_samples=block, progress=False,
                          cluster=ClusterConfig(workers=workers), options=SampleOptions(lidar_sweeps=lidar_sweeps))
        return build_store(cfg, client=client).n_samples

    return Job(name, run, out)


def labels_job(world: World, tmp: Path) -> Job:
    """`occdata labels --all-sweeps` into `tmp/<tag>`; the warm run labels one scene per worker."""
    from occdata.labels import LabelOptions, LabelsConfig, generate_labels

    def run(tag: str, client: Any, workers: int, scenes: tuple[str, ...] | None = None) -> int:
        cfg = LabelsConfig(root=world.root, out=tmp / tag, options=LabelOptions(all_sweeps=True), progress=False,
                           scenes=scenes, cluster=ClusterConfig(workers=workers))
        return generate_labels(cfg, client=client).keyframes

    def warm(tag: str, client: Any, workers: int) -> int:
        return run(tag, client, workers, tuple(name for name, _ in world.scenes[:workers]))

    return Job("labels", run, lambda tag: tmp / tag, warm)


def _timed_runs(job: Job, workers: int, client: Any, rounds: int, server_pid: int | None,
                warm: bool = True, first: int = 0) -> list[dict[str, Any]]:
    """One warm run (if `warm`), then `rounds` measured ones numbered from `first` (outputs removed
    after each)."""
    if warm:
        _log(f"{job.name}, {workers} worker(s): warm-up")
        (job.warm or job.run)(f"w{workers}_warm", client, workers)
        _drop(job.out(f"w{workers}_warm"))
    runs = []
    for r in range(first, first + rounds):
        tag = f"w{workers}_r{r}"
        _log(f"{job.name}, {workers} worker(s): timed run {r + 1}")
        rec = measure(functools.partial(job.run, tag, client, workers), client, server_pid)
        stored = _stored_bytes(job.out(tag))
        if stored is not None:
            rec["stored_bytes_per_unit"] = stored / rec["units"]
            rec["written_over_stored"] = rec["written_bytes_per_unit"] / rec["stored_bytes_per_unit"]
        _drop(job.out(tag))
        runs.append(rec)
    return runs


def _fastest(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The fastest run, plus all the times."""
    return min(runs, key=lambda r: r["seconds"]) | {"seconds_all": [r["seconds"] for r in runs]}


def bench_scaling(job: Job, workers: Sequence[int], rounds: int = 1, server_pid: int | None = None,
                  on_cluster: Callable[[Any], dict[str, Any]] | None = None,
                  interleave: bool = False) -> dict[str, Any]:
    """`job` at each worker count (1: in this process); `on_cluster(client)` adds figures taken on
    the last cluster (e.g. Dask's round trip). `interleave`: round by round, every worker count in
    turn (a fresh cluster each round), so that a host whose speed drifts between minutes (this VM's
    per-sample CPU moved by 30% between runs ten minutes apart) drifts within each round's pair;
    `paired_speedup_W_over_1` gives each round's own ratio."""
    out: dict[str, Any] = {}
    runs: dict[int, list[dict[str, Any]]] = {w: [] for w in workers}
    passes, per_pass = (rounds, 1) if interleave else (1, rounds)
    for r in range(passes):
        for w in workers:
            t0 = time.perf_counter()
            with cluster_client(ClusterConfig(workers=w)) as client:
                if client is not None:
                    out[f"localcluster_{w}_startup_s"] = time.perf_counter() - t0
                runs[w] += _timed_runs(job, w, client, per_pass, server_pid, warm=r == 0, first=r)
                if client is not None and on_cluster is not None and r == passes - 1:
                    out |= on_cluster(client)
    out |= {f"workers_{w}": _fastest(runs[w]) for w in workers}
    if "workers_1" in out:
        for w in (w for w in workers if w != 1):
            out[f"speedup_{w}_over_1"] = out[f"workers_{w}"]["units_per_s"] / out["workers_1"]["units_per_s"]
            pairs = zip(runs[1], runs[w], strict=True)
            out[f"paired_speedup_{w}_over_1"] = [a["seconds"] / b["seconds"] for a, b in pairs]
    return out


def bench_build(world: World, base: Path | str, workers: Sequence[int], rounds: int, lidar_sweeps: int,
                block: int, server_pid: int | None = None, name: str = "build",
                interleave: bool = False) -> dict[str, Any]:
    """`occdata build --lidar-sweeps N` at each worker count, with the block granularity's ceiling."""
    sizes = [min(block, world.samples - i) for i in range(0, world.samples, block)]
    out = {"blocks": len(sizes), "block_samples": block,
           **{f"ceiling_{w}_over_1": block_ceiling(sizes, w) for w in workers if w > 1}}
    extra = (lambda client: {"dask_overhead": bench_overhead(client)}) if server_pid is None else None
    return out | bench_scaling(build_job(world, base, lidar_sweeps, block, name), workers, rounds, server_pid, extra,
                               interleave)


def bench_labels(world: World, tmp: Path, workers: Sequence[int], rounds: int) -> dict[str, Any]:
    """`occdata labels --all-sweeps` (one task per scene) at each worker count (keyframes/s)."""
    sizes = [n for _, n in world.scenes]
    out = {"scenes": len(sizes), **{f"ceiling_{w}_over_1": block_ceiling(sizes, w) for w in workers if w > 1}}
    return out | bench_scaling(labels_job(world, tmp), workers, rounds)


def _bytes_written() -> int:
    """Bytes this process has passed to write(2) so far (Linux /proc/self/io `wchar`)."""
    with open("/proc/self/io") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("wchar:"))


def bench_bytes(root: Path, gts: Path | None, block: int, tmp: Path, lidar_sweeps: int = 0) -> dict[str, Any]:
    """Bytes written per sample / bytes stored per sample for one build in this process (1 worker:
    every write of the build is this process's). Goal: 1.0x; a schema-1 build (staging object) wrote ~2x."""
    from occdata.store.sample import SampleOptions

    out_store = tmp / "bytes.zarr"
    before = _bytes_written()
    report = build_store(BuildConfig(root=root, out=out_store, gts=gts, block_samples=block, progress=False,
                                     options=SampleOptions(lidar_sweeps=lidar_sweeps)))
    written = _bytes_written() - before
    stored = sum(p.stat().st_size for p in out_store.rglob("*") if p.is_file())
    flat = sum(p.stat().st_size for name in ("images", "depth") for p in (out_store / name).rglob("*")
               if p.is_file())
    shutil.rmtree(out_store, ignore_errors=True)
    n = report.n_samples
    return {"samples": n, "lidar_sweeps": lidar_sweeps, "written_per_sample": written / n,
            "stored_per_sample": stored / n, "ragged_stored_per_sample": flat / n,
            "written_over_stored": written / stored}


def bench_overhead(client: Any, n: int = 200) -> dict[str, float]:
    """Per-task cost of the scheduler round trips: empty tasks through run_tasks (window of 4)."""
    t0 = time.perf_counter()
    run_tasks(client, [_Noop() for _ in range(n)], desc="noop", progress=False, window=4)
    return {"tasks": n, "seconds_per_task": (time.perf_counter() - t0) / n}


# --- the write path alone --------------------------------------------------------------------------------
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


def _flat_rows(name: str, block: int, chunk: int) -> int:
    per = JPEG_BYTES_PER_SAMPLE if name == "images/jpeg" else UVD_ROWS_PER_SAMPLE
    return -(-(per * block) // chunk) * chunk


def _write_blocks(args: tuple[str, list[int], int, int, Any]) -> tuple[int, float, float]:
    """One writer process: whole blocks of fixed rows + its chunk-aligned flat regions. The payloads
    are made first; all writers start together (barrier). Returns (bytes, start, end) wall times."""
    from occdata.store.blocks import open_for_task

    store, blocks, block, n, barrier = args
    rng = np.random.default_rng(blocks[0] if blocks else 0)
    todo = []
    for b in blocks:
        i0, i1 = b * block, min(n, (b + 1) * block)
        flat = {}
        for name, (row, dtype, chunk) in FLAT_ARRAYS.items():
            rows = _flat_rows(name, block, chunk)
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
            root[name][start : start + len(data)] = data
            written += data.nbytes
        root["status/state"][i0:i1] = 1
    return written, t0, time.time()


def _fresh_store(url: str, n: int, block: int) -> None:
    import zarr

    from occdata.store.build import consolidate

    root = zarr.open_group(url, mode="w")
    create_arrays(root, n, block, {"schema": "bench"}, 32)
    for name, (row, _, chunk) in FLAT_ARRAYS.items():
        root[name].resize((_flat_rows(name, block, chunk) * (-(-n // block)), *row))
    consolidate(url)


def bench_write(url_of: Callable[[int], str], n: int, block: int, writers: tuple[int, ...]) -> dict[str, Any]:
    out = {}
    ctx = mp.get_context("spawn")
    for p in writers:
        _log(f"write path, {p} writer(s): {url_of(p)}")
        url = url_of(p)
        _fresh_store(url, n, block)
        blocks = list(range(-(-n // block)))
        with ctx.Manager() as manager, ctx.Pool(p) as pool:
            barrier = manager.Barrier(p)
            done = pool.map(_write_blocks, [(url, blocks[k::p], block, n, barrier) for k in range(p)])
        nbytes = sum(d[0] for d in done)
        dt = max(d[2] for d in done) - min(d[1] for d in done)
        out[f"writers_{p}"] = {"seconds": dt, "samples_per_s": n / dt, "MB_per_s": nbytes / dt / 1e6}
        _drop(url)
    return out


@contextmanager
def s3_server() -> Iterator[tuple[str, int]]:
    """A local S3 server (moto, its own process on 127.0.0.1) with a bucket; the environment points
    fsspec (and LocalCluster workers started meanwhile) at it. Yields (the bucket's URL, the pid)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "bench",
           "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for_port(port, "moto server")
        import fsspec

        fsspec.filesystem("s3").clear_instance_cache()
        fsspec.filesystem("s3").mkdir("bench")
        yield "s3://bench", proc.pid
    finally:
        proc.kill()
        proc.wait()
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# --- the run ---------------------------------------------------------------------------------------------
def _world_facts(world: World, args: argparse.Namespace) -> dict[str, Any]:
    return {"root": str(world.root), "samples": world.samples, "scenes": len(world.scenes),
            "keyframes_per_scene": sorted({n for _, n in world.scenes}), "image_size": list(world.image_size),
            "lidar_sweeps": args.lidar_sweeps, "block_samples": args.block_samples, "workers": args.workers,
            "rounds": args.rounds, "threads_per_process": args.threads or "library defaults"}


def run_sections(args: argparse.Namespace, world: World, tmp: Path,
                 save: Callable[[dict[str, Any]], None] = lambda res: None) -> dict[str, Any]:
    """The chosen sections (`args.sections`) in order; `save(result so far)` after each."""
    res: dict[str, Any] = {"world": _world_facts(world, args)}
    sweeps, block, workers, rounds = args.lidar_sweeps, args.block_samples, args.workers, args.rounds
    if "bytes" in args.sections:
        _log("bytes written / stored")
        res["bytes"] = bench_bytes(world.root, world.gts, block, tmp, sweeps)
        save(res)
    if "build" in args.sections:
        res["build"] = bench_build(world, tmp, workers, rounds, sweeps, block, interleave=args.interleave)
        save(res)
    if "s3" in args.sections:
        with s3_server() as (bucket, pid):
            res["build_s3"] = bench_build(world, bucket, workers, rounds, sweeps, block, pid, "build_s3")
            save(res)
            if "write" in args.sections:
                res["write_s3_moto"] = bench_write(lambda p: f"{bucket}/wr{p}.zarr", args.write_samples, 32,
                                                   tuple(args.writers))
                save(res)
    if "labels" in args.sections:
        res["labels"] = bench_labels(world, tmp, workers, rounds)
        save(res)
    if "write" in args.sections:
        res["write_local"] = bench_write(lambda p: str(tmp / f"wr{p}.zarr"), args.write_samples, 32,
                                         tuple(args.writers))
        save(res)
    if args.profile is not None:
        tools = args.profile_tools or available_profilers()
        _log(f"profiled CLI builds ({', '.join(tools) or 'no profiler installed'}) into {args.profile}")
        res["profile"] = profile_builds(world.root, world.gts, tmp, args.profile, tools, workers, sweeps, block)
        save(res)
    return res


# --- the text table ----------------------------------------------------------------------------------------
def _get(rec: dict[str, Any] | None, path: str) -> Any:
    for key in path.split("."):
        rec = rec.get(key) if isinstance(rec, dict) else None
    return rec


ROWS = (  # label ({unit}: the section's unit), path in a run record, format, whether to show 2/1
    ("{unit}s/s", "units_per_s", "{:.2f}", True),
    ("CPU user, s/{unit}", "cpu_s_per_unit.user", "{:.3f}", True),
    ("CPU kernel, s/{unit}", "cpu_s_per_unit.sys", "{:.3f}", True),
    ("kernel share of CPU", "kernel_share", "{:.0%}", False),
    ("client share of CPU", "client_share", "{:.0%}", False),
    ("cores busy (CPU / wall)", "cores_busy", "{:.2f}", False),
    ("workers busy in tasks (task stream)", "worker_busy_share", "{:.0%}", False),
    ("start to first task, s", "first_task_s", "{:.2f}", False),
    ("start-up share of the run", "startup_share", "{:.1%}", False),
    ("client CPU before the first task, s", "client_cpu_before_first_task_s", "{:.2f}", False),
    ("context switches/{unit}, voluntary", "context_switches_per_unit.voluntary", "{:.0f}", False),
    ("context switches/{unit}, involuntary", "context_switches_per_unit.involuntary", "{:.0f}", False),
    ("written / stored bytes", "written_over_stored", "{:.3f}", False),
    ("S3 server CPU user, s/{unit}", "server_cpu_s_per_unit.user", "{:.3f}", False),
    ("S3 server CPU kernel, s/{unit}", "server_cpu_s_per_unit.sys", "{:.3f}", False),
    ("peak RSS per worker, MiB", "worker_peak_rss_mib", "{:.0f}", False),
)


def _cell(value: Any, fmt: str) -> str:
    if isinstance(value, list):  # one value per worker
        return "/".join(f"{v:.0f}" for v in value)
    return "-" if value is None else fmt.format(value)


def _section_table(title: str, sec: dict[str, Any], unit: str) -> list[str]:
    a, b = sec.get("workers_1"), sec.get("workers_2")
    ceiling = sec.get("ceiling_2_over_1")
    lines = [f"{title}" + (f" (ceiling from task sizes at 2 workers: {ceiling:.2f}x)" if ceiling else "")]
    for label, path, fmt, ratio in ROWS:
        va, vb = _get(a, path), _get(b, path)
        if va is None and vb is None:
            continue
        r = f"{vb / va:.2f}x" if ratio and isinstance(va, float) and isinstance(vb, float) and va else ""
        lines.append(f"  {label.format(unit=unit):40}{_cell(va, fmt):>12}{_cell(vb, fmt):>14}{r:>8}")
    if paired := sec.get("paired_speedup_2_over_1"):
        lines.append(f"  {'2/1 within each round':40}{'':>12}{'':>14}  " + ", ".join(f"{x:.2f}x" for x in paired))
    if "localcluster_2_startup_s" in sec:
        lines.append(f"  {'LocalCluster start-up (not counted), s':40}{'':>12}{sec['localcluster_2_startup_s']:>14.2f}")
    return lines


def format_table(res: dict[str, Any]) -> str:
    """A compact text table of a result (any subset of the sections)."""
    w = res.get("world", {})
    lines = [f"world: {w.get('samples')} samples, {w.get('scenes')} scenes, {w.get('image_size')}, "
             f"--lidar-sweeps {w.get('lidar_sweeps')}, blocks of {w.get('block_samples')}, "
             f"threads per process: {w.get('threads_per_process')}, rounds: {w.get('rounds')}",
             f"  {'':40}{'1 worker':>12}{'2 workers':>14}{'2/1':>8}"]
    for key, title, unit in (("build", "occdata build, local disk", "sample"),
                             ("build_s3", "occdata build, S3 (moto on 127.0.0.1)", "sample"),
                             ("labels", "occdata labels --all-sweeps", "keyframe")):
        if key in res:
            lines += _section_table(title, res[key], unit)
    if "bytes" in res:
        b = res["bytes"]
        lines.append(f"bytes, one process: written {b['written_per_sample'] / 1e6:.2f} MB/sample, stored "
                     f"{b['stored_per_sample'] / 1e6:.2f} MB/sample: {b['written_over_stored']:.3f}x")
    if (trip := _get(res, "build.dask_overhead.seconds_per_task")) is not None:
        lines.append(f"Dask round trip per empty task: {trip * 1e3:.1f} ms")
    for key, title in (("write_local", "write path, local disk"), ("write_s3_moto", "write path, S3 (moto)")):
        if key in res:
            cells = ", ".join(f"P={k.split('_')[1]}: {v['MB_per_s']:.0f} MB/s" for k, v in res[key].items())
            lines.append(f"{title}: {cells}")
    for name, p in (res.get("profile") or {}).items():
        if isinstance(p, dict) and "summary" in p:
            lines.append(f"profile {name} ({p['seconds']:.1f} s, rc {p['returncode']}): {p['file']}")
    return "\n".join(lines)


# --- command line -------------------------------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    tools = available_profilers()
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, help="an existing nuScenes-format tree (else a synthetic world)")
    ap.add_argument("--gts", type=Path)
    ap.add_argument("--world", type=Path, help="where the synthetic world is made, once (default: a temporary one)")
    ap.add_argument("--synth-scenes", type=int, default=2)
    ap.add_argument("--synth-samples", type=int, default=40, help="synthetic keyframes in all (split over the scenes)")
    ap.add_argument("--synth-seed", type=int, default=0)
    ap.add_argument("--block-samples", type=int, default=BuildConfig.block_samples,
                    help="samples per build task (default: the build's own)")
    ap.add_argument("--lidar-sweeps", type=int, default=9, help="occdata build --lidar-sweeps N, for every build")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts (1: in this process)")
    ap.add_argument("--rounds", type=int, default=1, help="timed runs per figure (the fastest is kept)")
    ap.add_argument("--interleave", action="store_true",
                    help="build: round by round, each worker count in turn (paired ratios on a drifting host)")
    ap.add_argument("--threads", type=int, default=1, help="threads per process (0: the libraries' defaults)")
    ap.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated, of {','.join(SECTIONS)}")
    ap.add_argument("--write-samples", type=int, default=256)
    ap.add_argument("--writers", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--no-s3", action="store_true", help="no S3 server: drops the s3 section")
    ap.add_argument("--bytes-only", action="store_true", help="only the bytes written / stored figure")
    ap.add_argument("--profile", type=Path, metavar="DIR",
                    help="also run the CLI build under each profiler into DIR (found here: "
                         f"{', '.join(tools) or 'none'}; of {', '.join(PROFILE_TOOLS)})")
    ap.add_argument("--profile-tools", type=lambda s: s.split(","), default=None,
                    help="comma-separated (default: every one installed)")
    ap.add_argument("--tmp", type=Path, default=None, help="work folder's parent (stores, labels; ~1 GB)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    args.sections = ("bytes",) if args.bytes_only else tuple(s for s in args.sections.split(",")
                                                           if s and not (s == "s3" and args.no_s3))
    unknown = set(args.sections) - set(SECTIONS) | set(args.profile_tools or ()) - set(PROFILE_TOOLS)
    if unknown:
        ap.error(f"unknown sections or profilers: {sorted(unknown)}")
    return args


def _pin_threads(threads: int) -> None:
    """One thread per process: numba reads NUMBA_NUM_THREADS at import (and the LocalCluster's workers
    inherit the environment), so set the variables and re-execute this command once."""
    if threads <= 0:
        return
    want = {k: str(threads) for k in THREAD_ENV}
    if any(os.environ.get(k) != v for k, v in want.items()):
        os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], {**os.environ, **want})
    import cv2

    cv2.setNumThreads(threads)


def _thread_facts() -> dict[str, Any]:
    import zarr

    return {"env": {k: os.environ.get(k) for k in THREAD_ENV},
            "zarr_threading_max_workers": zarr.config.get("threading.max_workers", None),
            "zarr_async_concurrency": zarr.config.get("async.concurrency", None)}


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if argv is None:  # the command line (never re-execute a caller such as a test)
        _pin_threads(args.threads)
    record = machine(note="2-core VM: run alone on the machine (loadavg_1min ~0 at the start)",
                     threads=_thread_facts())
    tmp = Path(tempfile.mkdtemp(prefix="bench_scale_", dir=args.tmp))

    def save(res: dict[str, Any]) -> None:  # after each section: a failure later keeps what was measured
        if args.json is not None:
            write_json({"machine": record} | res, args.json)

    try:
        world = make_world(args, tmp)
        result = {"machine": record} | run_sections(args, world, tmp, save)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    finish(record)
    if args.json is not None:
        write_json(result, args.json)
    else:
        emit_json(result, None)
    print(format_table(result))


if __name__ == "__main__":
    main()
