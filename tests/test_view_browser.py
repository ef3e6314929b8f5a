"""`occdata view` in a real browser: headless Chromium (the Debian package, software WebGL) driven by
Playwright loads the live viewer and the exported HTML file and the test reads the screenshots.

Flat style draws voxels unlit in the exact class colours, so a class is "on screen" when pixels of
exactly its colour are. No request may leave 127.0.0.1 (or file://). Set OCCDATA_VIEW_SHOTS=DIR to keep
the screenshots (docs/view.md shows them)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from conftest import missing_fixture

from occdata.constants import CLASS_COLORS, FREE_LABEL
from occdata.view.source import ViewSource
from occdata.view.voxels import ERROR_COLORS

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
VIEWPORT = {"width": 1200, "height": 800}
SCENE_AREA = (slice(160, 800), slice(0, 850))  # below the software-WebGL notice, left of the control panel
LOCAL = ("http://127.0.0.1", "ws://127.0.0.1", "file://", "blob:", "data:")


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[object]:
    if not Path(CHROMIUM).exists():
        missing_fixture("Chromium", Path(CHROMIUM), "apt-get install chromium; .ci/run does")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(str(tmp_path_factory.mktemp("chromium")), executable_path=CHROMIUM,
                                                   args=FLAGS, viewport=VIEWPORT)
        try:
            yield ctx
        finally:
            ctx.close()


@contextmanager
def page_of(ctx: object, url: str) -> Iterator[object]:
    """A page at `url` that refuses (and records) every request that is not local."""
    page = ctx.new_page()  # type: ignore[attr-defined]
    outside: list[str] = []

    def route(r: object) -> None:
        url_ = r.request.url  # type: ignore[attr-defined]
        if url_.startswith(LOCAL):
            r.continue_()  # type: ignore[attr-defined]
        else:
            outside.append(url_)
            r.abort()  # type: ignore[attr-defined]

    page.route("**/*", route)
    page.goto(url)
    try:
        yield page
    finally:
        page.close()
    assert not outside, f"the page asked the network for {outside[:3]}"


@contextmanager
def viewer(*args: str) -> Iterator[str]:
    """`occdata view ... --port 0` as a subprocess; yields its URL; stopped with Ctrl-C (SIGINT)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "cli.occdata_cli", "view", *args, "--port", "0"], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url, lines, t0 = None, [], time.time()
        while url is None and time.time() - t0 < 90:
            line = proc.stdout.readline()  # type: ignore[union-attr]
            if not line and proc.poll() is not None:
                break
            lines.append(line)
            m = re.search(r"occdata view: (http://127\.0\.0\.1:\d+)", line)
            url = m.group(1) if m else None
        assert url, f"no URL from occdata view: {''.join(lines)}"
        yield url
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, proc.returncode


def wait_status(page: object, pattern: str, timeout_s: float = 120) -> str:
    """Wait until the page text matches `pattern` (a regex); returns the match."""
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        m = re.search(pattern, page.inner_text("body"))  # type: ignore[attr-defined]
        if m:
            return m.group(0)
        time.sleep(0.3)
    raise AssertionError(f"page never showed /{pattern}/; it shows: {page.inner_text('body')[:500]}")  # type: ignore


def settled_shot(page: object, name: str, tmp: Path, timeout_s: float = 60) -> np.ndarray:
    """Screenshot once two in a row agree (the canvas renders on demand); RGB of the scene area."""
    import cv2

    prev, deadline = None, time.time() + timeout_s
    path = tmp / f"{name}.png"
    while True:
        page.screenshot(path=str(path))  # type: ignore[attr-defined]
        img = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        if prev is not None and np.array_equal(img, prev) or time.time() > deadline:
            break
        prev = img
        time.sleep(1.0)
    keep = os.environ.get("OCCDATA_VIEW_SHOTS")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(keep) / path.name)
    return img[SCENE_AREA]


def choose(page: object, label: str, option: str) -> None:
    """Pick `option` in the control panel's drop-down `label` (a Mantine combobox)."""
    page.get_by_role("combobox", name=label).click()  # type: ignore[attr-defined]
    page.get_by_role("option", name=option, exact=True).click()  # type: ignore[attr-defined]


def color_pixels(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 2) -> int:
    return int((np.abs(img.astype(int) - np.array(rgb)).max(axis=-1) <= tol).sum())


def background_fraction(img: np.ndarray) -> float:
    """Share of the scene area in the most common colour (the empty canvas)."""
    _, counts = np.unique(img.reshape(-1, 3), axis=0, return_counts=True)
    return float(counts.max() / counts.sum())


def _big_classes(semantics: np.ndarray, min_voxels: int = 300) -> tuple[list[int], list[int]]:
    counts = np.bincount(semantics.ravel(), minlength=FREE_LABEL + 1)
    return ([c for c in range(FREE_LABEL) if counts[c] >= min_voxels],
            [c for c in range(FREE_LABEL) if counts[c] == 0])


@pytest.fixture(scope="module")
def preds(synth_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Predictions that differ from the labels: cars become trucks (wrong), pedestrians vanish (missed)."""
    src = ViewSource(synth_store)
    out = tmp_path_factory.mktemp("pred")
    for scene in src.scenes:
        for pos in range(len(scene.indices)):
            s = src.sample(scene, pos)
            pred = s.semantics.copy()
            pred[pred == 4] = 10
            pred[pred == 7] = FREE_LABEL
            (out / scene.name / s.token).mkdir(parents=True)
            np.savez_compressed(out / scene.name / s.token / "labels.npz", semantics=pred)
    return out


@pytest.mark.slow  # about 80 s on 2 shared cores with software WebGL; CI runs it (.ci/run)
def test_live_viewer_draws_steps_and_shows_errors(browser: object, synth_store: Path, preds: Path,
                                                  tmp_path: Path) -> None:
    src = ViewSource(synth_store)
    first = src.sample(src.scenes[0], 0)
    present, absent = _big_classes(first.semantics)
    with viewer("--store", str(synth_store), "--pred", str(preds), "--view", "label") as url, \
            page_of(browser, url) as page:
        wait_status(page, r"keyframe 1/3 · label view · sample \w+ · drawn in \d+ ms")
        label = settled_shot(page, "view_label", tmp_path)
        assert background_fraction(label) < 0.6
        for c in present:
            assert color_pixels(label, CLASS_COLORS[c]) >= 30, f"class {c} not on screen"
        for c in absent:
            assert color_pixels(label, CLASS_COLORS[c]) < 0.0005 * label.size / 3, f"absent class {c} on screen"

        page.get_by_role("button", name="next", exact=True).click()
        wait_status(page, r"keyframe 2/3 · label view · sample \w+ · drawn in \d+ ms")
        second = settled_shot(page, "view_label_next", tmp_path)
        assert (np.abs(second.astype(int) - label).max(axis=-1) > 10).mean() > 0.05

        choose(page, "Scene", src.scenes[1].title)
        wait_status(page, r"synth-0001\*?\*? · keyframe 1/3 · label view · sample \w+ · drawn in \d+ ms")
        other = settled_shot(page, "view_other_scene", tmp_path)
        assert (np.abs(other.astype(int) - second).max(axis=-1) > 10).mean() > 0.05

        choose(page, "View", "error (right / wrong / missed)")
        wait_status(page, r"keyframe 1/3 · error view · sample \w+ · drawn in \d+ ms")
        err = settled_shot(page, "view_error", tmp_path)
        for kind, rgb in zip(("right", "wrong", "missed"), ERROR_COLORS, strict=True):
            assert color_pixels(err, rgb) >= 30, f"error view lacks '{kind}' voxels"
        assert color_pixels(err, CLASS_COLORS[11]) < 0.0005 * err.size / 3  # no class colours in the error view

        choose(page, "View", "label | prediction")
        choose(page, "Mask", "camera")
        wait_status(page, r"keyframe 1/3 · label \| prediction view · mask camera · sample \w+ · drawn in \d+ ms")
        side = settled_shot(page, "view_side_camera_mask", tmp_path)
        assert color_pixels(side, (150, 150, 150)) >= 30  # voxels outside the camera mask, grey


def test_exported_file_renders_offline(browser: object, synth_store: Path, tmp_path: Path) -> None:
    out = tmp_path / "scene.html"
    r = subprocess.run([sys.executable, "-m", "cli.occdata_cli", "view", "--store", str(synth_store), "--export",
                        str(out)], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "3 keyframes" in r.stdout and out.stat().st_size > 100_000
    src = ViewSource(synth_store)
    common = set(range(FREE_LABEL))
    for pos in range(3):
        common &= set(_big_classes(src.sample(src.scenes[0], pos).semantics, 2000)[0])
    assert common
    with page_of(browser, out.as_uri()) as page:
        deadline = time.time() + 150  # the file decodes its scene, then fades its loading veil out
        while True:
            img = settled_shot(page, "view_export", tmp_path, timeout_s=1)
            missing = [c for c in common if color_pixels(img, CLASS_COLORS[c]) < 30]
            if not missing or time.time() > deadline:
                break
            time.sleep(2.0)
        assert background_fraction(img) < 0.6, "the exported file shows an empty canvas"
        assert not missing, f"classes {missing} not drawn in the export"


def test_pages_without_data_say_so(browser: object, synth_root: Path, synth_store: Path, tmp_path: Path) -> None:
    from occdata.store.build import BuildConfig, build_store

    with viewer("--store", str(synth_store), "--split", "test") as url, page_of(browser, url) as page:
        wait_status(page, r"No samples to show: split 'test' has no built samples", timeout_s=60)
        settled_shot(page, "view_empty_split", tmp_path, timeout_s=10)
    unlabelled = tmp_path / "nolabels.zarr"
    build_store(BuildConfig(root=synth_root, out=unlabelled, gts=None, progress=False))
    with viewer("--store", str(unlabelled)) as url, page_of(browser, url) as page:
        wait_status(page, r"No labels for this sample", timeout_s=60)
        img = settled_shot(page, "view_no_labels", tmp_path, timeout_s=20)
        assert background_fraction(img) < 0.995  # the cameras are still drawn, not a blank canvas
