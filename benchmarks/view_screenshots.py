"""Screenshots of `occdata view` in headless Chromium for docs/view.md, on any store (the demo's):

    python -m benchmarks.view_screenshots --store demo/data.zarr --pred demo/pred --split val --out docs/img/view

One viewer per view (`--view label | side | error`, the side view with the camera mask, the LiDAR
layer on), each started on 127.0.0.1 with `--port 0`, shot once two screenshots in a row agree (the
canvas renders on demand) and stopped with Ctrl-C. Needs Debian's chromium and playwright (the
`dev` extra); nothing is fetched from the network.
"""

from __future__ import annotations

import argparse
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import CHROMIUM_FLAGS
from benchmarks.provenance import REPO

__all__ = ["SHOTS"]
SHOTS = {  # file name: extra `occdata view` options
    "demo_label": ["--view", "label"],
    "demo_side_camera_mask": ["--view", "side", "--mask", "camera"],
    "demo_error": ["--view", "error"],
    "demo_label_lidar": ["--view", "label", "--lidar"],
}


def _serve(args: list[str]) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "cli.occdata_cli", "view", *args, "--port", "0"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 120
    while time.time() < deadline:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        m = re.search(r"(http://127\.0\.0\.1:\d+)", line)
        if m:
            return proc, m.group(1)
        if not line and proc.poll() is not None:
            break
    proc.kill()
    raise SystemExit("occdata view printed no URL")


def _shot(page: object, path: Path, timeout_s: float = 180) -> None:
    deadline = time.time() + timeout_s
    while not re.search(r"drawn in \d+ ms", page.inner_text("body")) and time.time() < deadline:  # type: ignore
        time.sleep(0.5)
    prev = None
    while time.time() < deadline:
        page.screenshot(path=str(path))  # type: ignore[attr-defined]
        data = path.read_bytes()
        if data == prev:
            return
        prev = data
        time.sleep(1.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", required=True)
    ap.add_argument("--pred", default=None)
    ap.add_argument("--split", default=None)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright

    a.out.mkdir(parents=True, exist_ok=True)
    base = ["--store", a.store] + (["--pred", a.pred] if a.pred else []) + (["--split", a.split] if a.split else [])
    with sync_playwright() as p, tempfile.TemporaryDirectory() as profile:
        ctx = p.chromium.launch_persistent_context(profile, executable_path="/usr/bin/chromium", args=CHROMIUM_FLAGS,
                                                   viewport={"width": 1200, "height": 800})
        try:
            for name, extra in SHOTS.items():
                if "--view" in extra and extra[1] in ("side", "error") and not a.pred:
                    continue
                proc, url = _serve(base + extra)
                try:
                    page = ctx.new_page()
                    page.goto(url)
                    _shot(page, a.out / f"{name}.png")
                    page.close()
                    print("wrote", a.out / f"{name}.png", flush=True)
                finally:
                    proc.send_signal(signal.SIGINT)
                    try:
                        proc.wait(timeout=20)
                    except subprocess.TimeoutExpired:
                        proc.kill()
        finally:
            ctx.close()


if __name__ == "__main__":
    main()
