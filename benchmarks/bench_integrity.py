"""Cost of the store integrity checks on the read path.

Reads every done sample of a store through the loader's `StoreSamples.read_run` (one block at a
time, as the shuffled loader does), with the per-row checksum checks on and off (alternating
rounds, best of N), and times crc32 alone. Also times opening a reader and loading the small
arrays (chunk listing included).

    python -m benchmarks.bench_integrity --store data.zarr --rounds 5 --json out.json
"""

from __future__ import annotations

import argparse
import time
import zlib
from pathlib import Path

import numpy as np

from benchmarks.common import emit_json
from benchmarks.provenance import machine
from fastocc.data.sample import StoreSamples
from occdata.store import integrity
from occdata.store.reader import open_store

__all__: list[str] = []


def _read_all(store: str, check: bool) -> tuple[float, int, int]:
    real = integrity.StoreIntegrity.check_rows
    if not check:
        integrity.StoreIntegrity.check_rows = lambda self, *a, **k: None  # type: ignore[method-assign]
    try:
        samples = StoreSamples(open_store(store))
        done = np.flatnonzero(samples.state == 1)
        t0 = time.perf_counter()
        n_bytes = 0
        for b0 in range(0, int(done.max()) + 1, samples.block):
            for raw in samples.read_run(b0, min(b0 + samples.block, len(samples.state))):
                n_bytes += sum(a.nbytes for a in raw.jpegs) + sum(a.nbytes for a in raw.uvd)
                n_bytes += sum(v.nbytes for v in (raw.labels or {}).values())
        return time.perf_counter() - t0, len(done), n_bytes
    finally:
        integrity.StoreIntegrity.check_rows = real  # type: ignore[method-assign]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    record = machine()
    on, off = [], []
    for _ in range(args.rounds):
        t, n, nbytes = _read_all(args.store, check=True)
        on.append(t)
        t, n, nbytes = _read_all(args.store, check=False)
        off.append(t)
    blob = np.random.default_rng(0).integers(0, 255, 64 << 20, dtype=np.uint8).tobytes()
    t0 = time.perf_counter()
    zlib.crc32(blob)
    crc_gbps = len(blob) / (time.perf_counter() - t0) / 1e9
    t0 = time.perf_counter()
    r = open_store(args.store)
    for name in ("status/state", "labels/present", "calib/K", "calib/T_keyego_from_cam", "images/offsets",
                 "depth/offsets", "temporal/prev_index"):
        r.small(name)
    open_s = time.perf_counter() - t0
    out = {
        "store": args.store, "samples": n, "mb_per_sample": nbytes / n / 1e6,
        "read_ms_per_sample_checked": 1e3 * min(on) / n, "read_ms_per_sample_unchecked": 1e3 * min(off) / n,
        "check_overhead_ms_per_sample": 1e3 * (min(on) - min(off)) / n,
        "crc32_gb_per_s": crc_gbps, "open_and_small_arrays_s": open_s, "machine": record,
    }
    emit_json(out, args.json)


if __name__ == "__main__":
    main()
