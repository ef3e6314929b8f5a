"""How far this machine's cores scale on their own: the same work in one
process, then in one process per core at once, for a pure-Python loop, JPEG decoding + resizing with
OpenCV (what a build task does most) and large memory copies.

Research: the machine's own limit, read beside the build's scale figures (docs/scale.md). Indexed in
benchmarks/README.md.

    python -m benchmarks.bench_cores [--processes 2] [--json out.json]

The figure is the throughput ratio, P x (one process's time) / (from the first of P processes' start
to the last one's end), the median of `--rounds`. Run it alone: on this project's shared VM single
rounds range from 1.0x to 2.1x.
"""

from __future__ import annotations

import argparse
import time
from multiprocessing import get_context

import numpy as np

from benchmarks.common import emit_json
from benchmarks.provenance import machine

__all__: list[str] = []


# Each returns its (start, end) on CLOCK_MONOTONIC, which all processes share: the P-process figure is the
# makespan, so work that ran one after the other is not mistaken for work that ran side by side.
Span = tuple[float, float]


def python_loop(_: int) -> Span:
    t0, x = time.monotonic(), 0
    for i in range(6_000_000):
        x += i * i
    return t0, time.monotonic()


def jpeg_decode_resize(_: int) -> Span:
    import cv2

    cv2.setNumThreads(1)
    img = (np.random.default_rng(0).random((900, 1600, 3)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    t0 = time.monotonic()
    for _ in range(60):
        cv2.resize(cv2.imdecode(buf, cv2.IMREAD_COLOR), (704, 396))
    return t0, time.monotonic()


def memory_copy(_: int) -> Span:
    a = np.ones(64 << 20, np.uint8)
    b = np.empty_like(a)
    np.copyto(b, a)  # pages in before timing
    t0 = time.monotonic()
    for _ in range(40):
        np.copyto(b, a)
    return t0, time.monotonic()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=5, help="alternating 1 / P rounds; the median ratio is the figure")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    out: dict[str, object] = {"machine": machine(), "processes": a.processes, "rounds": a.rounds}
    with get_context("spawn").Pool(a.processes) as pool:
        for work in (python_loop, jpeg_decode_resize, memory_copy):
            pool.map(work, range(a.processes), chunksize=1)  # warm: imports, page cache
            ratios = []
            for _ in range(a.rounds):  # alternated, so a burst of load on the shared host hits both sides
                t0, t1 = pool.apply(work, (0,))
                spans = pool.map(work, range(a.processes), chunksize=1)
                makespan = max(e for _, e in spans) - min(s for s, _ in spans)
                ratios.append(a.processes * (t1 - t0) / makespan)
            out[work.__name__] = {"ratio_median": float(np.median(ratios)), "ratios": ratios}
    emit_json(out, a.json)


if __name__ == "__main__":
    main()
