"""`occdata view`: time from a keyframe switch request to the browser having drawn it.

Starts `occdata view --store STORE --port 0`, loads it in headless Chromium (system package, software
WebGL), presses "next" N times and reads the viewer's own figure ("drawn in X ms": server receives the
request -> reads and composes the keyframe -> sends it -> the browser applies it and renders a frame, the
`get_render` round trip). Also times the server-side part alone (store read + layers) in this process.

    python -m benchmarks.bench_view_switch --store /tmp/s40.zarr --steps 15 --json
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import statistics
import subprocess
import sys
import time

from benchmarks.common import CHROMIUM_FLAGS
from benchmarks.provenance import REPO, machine

__all__ = ["browser_ms", "server_side_ms"]


def server_side_ms(store: str, steps: int, style: str) -> list[float]:
    from occdata.view.config import FrameOptions
    from occdata.view.frame import compose_frame
    from occdata.view.source import ViewSource

    src = ViewSource(store)
    scene, out = src.scenes[0], []
    for k in range(steps):
        t = time.perf_counter()
        s = src.sample(scene, (k + 1) % len(scene.indices), images=True)
        frame = compose_frame(s, FrameOptions(style=style))  # type: ignore[arg-type]
        out.append(1000 * (time.perf_counter() - t))
        assert frame.groups
    return out


def browser_ms(store: str, steps: int, style: str) -> tuple[list[float], int]:
    from playwright.sync_api import sync_playwright

    proc = subprocess.Popen([sys.executable, "-m", "cli.occdata_cli", "view", "--store", store, "--port", "0",
                             "--style", style], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = None
        while url is None:
            m = re.search(r"occdata view: (http://\S+)", proc.stdout.readline())  # type: ignore[union-attr]
            url = m.group(1) if m else None
        times = []
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_FLAGS)
            page = b.new_page(viewport={"width": 1200, "height": 800})
            page.goto(url)
            pat = r"keyframe (\d+)/(\d+) · .*? · drawn in (\d+) ms"
            n_voxels = 0
            for k in range(steps + 1):
                want = k + 1
                deadline = time.time() + 120
                while time.time() < deadline:
                    m = re.search(pat, page.inner_text("body"))
                    if m and int(m.group(1)) == want:
                        break
                    time.sleep(0.05)
                else:
                    raise RuntimeError(f"keyframe {want} never drawn")
                if k:  # the first figure is the page load
                    times.append(float(m.group(3)))
                n_voxels = int(m.group(2))
                if k < steps:
                    page.get_by_role("button", name="next", exact=True).click()
            b.close()
        return times, n_voxels
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--steps", type=int, default=15)
    ap.add_argument("--style", default="flat", choices=["flat", "cubes"])
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    record = machine()
    server = server_side_ms(a.store, a.steps, a.style)
    drawn, n_keyframes = browser_ms(a.store, a.steps, a.style)
    res = {"store": a.store, "style": a.style, "steps": a.steps, "keyframes_in_scene": n_keyframes,
           "server_read_compose_ms_median": round(statistics.median(server), 1),
           "request_to_drawn_ms_median": round(statistics.median(drawn), 1),
           "request_to_drawn_ms_max": round(max(drawn), 1), "request_to_drawn_ms": drawn,
           "browser": "headless Chromium, software WebGL (SwiftShader), 1200x800", "machine": record}
    print(json.dumps(res, indent=1) if a.json else
          f"switch: median {res['request_to_drawn_ms_median']} ms request -> drawn (max "
          f"{res['request_to_drawn_ms_max']}), server part {res['server_read_compose_ms_median']} ms")


if __name__ == "__main__":
    main()
