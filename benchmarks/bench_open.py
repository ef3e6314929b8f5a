"""Loader start: a store opened to the first batch, locally and over S3 behind a latency proxy, before/after.

For each store size (`--samples`, default 3,400 and 10,200), a store is made by replaying one built
block (`benchmarks/tiled_store.py`: the small arrays at full size, the payload hard-linked), then for each
code tree (`--trees`: `before=/work/main after=.` by default) a fresh Python process with that tree on
PYTHONPATH imports torch, zarr and fastocc (not timed), then times `make_loader(LoaderConfig(store,
batch_size=1))` ("open": the dataset's construction, where the small arrays are read) and the first
batch (`next(iter(loader))`, num_workers=0: the shuffle buffer's first blocks read and one sample
decoded), wall and CPU seconds (this process: user + kernel, all threads). Each figure is the
fastest of `--rounds`.

- local: the store on this disk (page cache warm after the first round);
- s3 (`--latency-ms`): the store uploaded to a local S3 server (moto, its own process on 127.0.0.1)
  and read through a forwarding proxy on 127.0.0.1 that sleeps `--latency-ms` before passing each
  request on, and counts them (real object stores add 10-50 ms per request).

The JSON records each run's seconds, the requests the proxy saw, the connects the kernel dropped during
the run (`tcp`: ListenOverflows and TCPSynRetrans of /proc/net/netstat, counted machine-wide; each resent
SYN stalls its request 1 s), the machine and the load average (this VM is shared: timings of other work
running alongside are inflated).

    python -m benchmarks.bench_open --src /tmp/src.zarr --work /tmp/bench_open --latency-ms 20 \\
        --json docs/results/bench_open.json
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]

# The timed child: imports first (not timed), then open and first batch. Prints one JSON line.
CHILD = r"""
import json, sys, time, warnings
warnings.simplefilter("ignore")
import torch, zarr, cv2
from fastocc.data.dataset import LoaderConfig, make_loader
store = sys.argv[1]
c0, t0 = time.process_time(), time.perf_counter()
loader = make_loader(LoaderConfig(store=store, batch_size=1), num_workers=0)
c1, t1 = time.process_time(), time.perf_counter()
batch = next(iter(loader))
c2, t2 = time.process_time(), time.perf_counter()
print(json.dumps({"open_s": t1 - t0, "first_batch_s": t2 - t1, "total_s": t2 - t0, "open_cpu_s": c1 - c0,
                  "first_batch_cpu_s": c2 - c1, "sample": int(batch.sample_index[0])}))
"""


class LatencyProxy(ThreadingHTTPServer):
    """An HTTP forwarding proxy on 127.0.0.1: each request waits `latency_s`, then goes to `upstream`."""

    daemon_threads = True
    # socketserver listens with a backlog of 5. The client opens its 10 pooled connections at once (the
    # concurrent zarr.json reads); when this accept thread was slow to get the GIL, one connect past the
    # backlog had its SYN dropped, and the client resent it after TCP's 1 s initial timeout: a ~1 s stall
    # now and then (more under load) that no real object store adds. moto, behind, listens with 128.
    request_queue_size = 128

    def __init__(self, upstream_port: int, latency_s: float) -> None:
        super().__init__(("127.0.0.1", 0), _Forward)
        self.upstream_port, self.latency_s = upstream_port, latency_s
        self.requests = 0
        self.log: list[str] = []  # "METHOD path" of each request
        self.lock = threading.Lock()


class _Forward(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"  # keep-alive, as clients of real object stores use

    def log_message(self, *args: Any) -> None:  # quiet
        pass

    def _forward(self) -> None:
        server: LatencyProxy = self.server  # type: ignore[assignment]
        with server.lock:
            server.requests += 1
            server.log.append(f"{self.command} {self.path}")
        body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
        time.sleep(server.latency_s)
        conn = http.client.HTTPConnection("127.0.0.1", server.upstream_port, timeout=60)
        headers = {k: v for k, v in self.headers.items() if k.lower() not in ("connection", "expect")}
        conn.request(self.command, self.path, body=body or None, headers=headers)
        resp = conn.getresponse()
        data = resp.read()
        conn.close()
        self.send_response(resp.status, resp.reason)
        for k, v in resp.getheaders():
            if k.lower() not in ("transfer-encoding", "connection", "content-length", "server", "date"):
                self.send_header(k, v)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(data)

    do_GET = do_PUT = do_POST = do_DELETE = do_HEAD = _forward


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def s3_with_proxy(latency_ms: float) -> Iterator[tuple[dict[str, str], dict[str, str], LatencyProxy]]:
    """A moto server and the proxy in front of it. Yields (env to reach S3 directly, env through the
    proxy, the proxy)."""
    from benchmarks.common import wait_for_port

    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    proxy = LatencyProxy(port, latency_ms / 1000)
    thread = threading.Thread(target=proxy.serve_forever, daemon=True)
    thread.start()
    creds = {"AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}
    try:
        wait_for_port(port, "moto server", tries=200)
        yield ({**creds, "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}"},
               {**creds, "AWS_ENDPOINT_URL": f"http://127.0.0.1:{proxy.server_address[1]}"}, proxy)
    finally:
        proxy.shutdown()
        proc.kill()
        proc.wait()


def upload(local: Path, url: str, env: dict[str, str]) -> None:
    """Copy a local store to S3 (directly, not through the proxy)."""
    code = ("import sys, fsspec; fs = fsspec.filesystem('s3'); bucket = sys.argv[2].split('/')[2]\n"
            "if not fs.exists(bucket): fs.mkdir(bucket)\nfs.put(sys.argv[1], sys.argv[2], recursive=True)")
    subprocess.run([sys.executable, "-c", code, str(local), url], env={**os.environ, **env}, check=True)


def time_start(tree: Path, store: str, env: dict[str, str] | None = None) -> dict[str, Any]:
    """One fresh process with `tree` first on PYTHONPATH: open and first batch (imports not timed)."""
    full = {**os.environ, **(env or {}), "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", CHILD, store], env=full, capture_output=True, text=True,
                         cwd=tree, timeout=600)
    if out.returncode:
        raise RuntimeError(f"{tree}: {out.stderr.strip().splitlines()[-1] if out.stderr.strip() else out.returncode}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def tcp_drops() -> dict[str, int]:
    """This network namespace's counts of connects dropped by a full accept queue and of resent SYNs
    (/proc/net/netstat; empty elsewhere). A resent SYN costs its connection 1 s."""
    want, out = ("ListenOverflows", "TCPSynRetrans"), {}
    try:
        lines = Path("/proc/net/netstat").read_text().splitlines()
    except OSError:
        return out
    for names, values in zip(lines[::2], lines[1::2], strict=False):
        for k, v in zip(names.split()[1:], values.split()[1:], strict=False):
            if k in want:
                out[k] = int(v)
    return out


def request_kinds(log: list[str]) -> dict[str, int]:
    """Requests by method and what they asked for: listings, metadata (zarr.json), chunk reads."""
    kinds: dict[str, int] = {}
    for line in log:
        method, path = line.split(" ", 1)
        what = "list" if "list-type" in path or "prefix=" in path else \
            "zarr.json" if path.split("?")[0].endswith("zarr.json") else "pack" if "/pack/" in path else "chunk"
        kinds[f"{method} {what}"] = kinds.get(f"{method} {what}", 0) + 1
    return dict(sorted(kinds.items()))


def best(runs: list[dict[str, Any]]) -> dict[str, Any]:
    return {**min(runs, key=lambda r: r["total_s"]), "rounds": [round(r["total_s"], 3) for r in runs],
            "rounds_open": [round(r["open_s"], 3) for r in runs],
            "rounds_syn_retrans": [r.get("tcp", {}).get("TCPSynRetrans") for r in runs]}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, required=True, help="a built store of exactly one block (tiled_store.py)")
    ap.add_argument("--work", type=Path, required=True, help="where the stores are made (deleted after)")
    ap.add_argument("--samples", type=int, nargs="+", default=[3400, 10200])
    ap.add_argument("--s3-samples", type=int, nargs="*", default=None, help="sizes also read over S3 (default: all)")
    ap.add_argument("--trees", nargs="+", default=["before=/work/main", "after=."], metavar="NAME=PATH")
    ap.add_argument("--latency-ms", type=float, default=20.0)
    ap.add_argument("--rounds", type=int, default=2, help="timed runs per local figure (the fastest is kept)")
    ap.add_argument("--s3-rounds", type=int, default=1, help="timed runs per S3 figure")
    ap.add_argument("--no-local", action="store_true", help="S3 figures only")
    ap.add_argument("--zero-latency-trees", nargs="*", default=["after"], metavar="NAME",
                    help="trees also timed over S3 with no added latency (what the latency itself costs)")
    ap.add_argument("--keep", action="store_true", help="keep the made stores")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    from benchmarks.provenance import finish, machine
    from benchmarks.tiled_store import make_tiled_store

    trees = {name: Path(path).resolve() for name, path in (t.split("=", 1) for t in args.trees)}
    s3_sizes = args.samples if args.s3_samples is None else args.s3_samples
    res: dict[str, Any] = {"machine": machine(), "latency_ms": args.latency_ms,
                           "trees": {k: str(v) for k, v in trees.items()}, "local": {}, "s3": {}}

    def save() -> None:
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(res, indent=1) + "\n")

    args.work.mkdir(parents=True, exist_ok=True)
    stores = {}
    for n in args.samples:
        stores[n] = make_tiled_store(args.src, args.work / f"tiled_{n}.zarr", n)
        if args.no_local:
            continue
        res["local"][str(n)] = {name: best([time_start(tree, str(stores[n])) for _ in range(args.rounds)])
                                for name, tree in trees.items()}
        print(n, "local", json.dumps(res["local"][str(n)]), flush=True)
        save()
    if s3_sizes:
        with s3_with_proxy(args.latency_ms) as (direct, proxied, proxy):
            for n in s3_sizes:
                url = f"s3://bench/tiled_{n}.zarr"
                upload(stores[n], url, direct)
                out = {}
                runs_at = [(name, tree, args.latency_ms) for name, tree in trees.items()]
                runs_at += [(f"{name}@0ms", trees[name], 0.0) for name in args.zero_latency_trees]
                for name, tree, latency in runs_at:
                    proxy.latency_s = latency / 1000
                    runs = []
                    for _ in range(args.s3_rounds):
                        before, drops = proxy.requests, tcp_drops()
                        run = time_start(tree, url, proxied)
                        runs.append({**run, "requests": proxy.requests - before,
                                     "by_kind": request_kinds(proxy.log[before:]),
                                     "tcp": {k: v - drops[k] for k, v in tcp_drops().items() if k in drops}})
                    out[name] = best(runs)
                proxy.latency_s = args.latency_ms / 1000
                res["s3"][str(n)] = out
                print(n, "s3", json.dumps(out), flush=True)
                save()
    finish(res["machine"])
    save()
    if not args.keep:
        for path in stores.values():
            shutil.rmtree(path, ignore_errors=True)


if __name__ == "__main__":
    main()
