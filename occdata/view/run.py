"""`occdata view`: serve the live viewer, or write one scene as a self-contained HTML file."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from occdata.errors import OccDataError
from occdata.fileio import write_atomic
from occdata.view.config import ViewConfig
from occdata.view.draw import SceneDrawer, add_legend_plane
from occdata.view.frame import SIDE_OFFSET_M, compose_frame
from occdata.view.source import SceneEntry, ViewSource
from occdata.view.voxels import N_SEMANTIC

__all__ = ["ExportReport", "export_html", "import_viser", "run_view", "serve"]

Echo = Callable[[str], None]


def import_viser() -> ModuleType:
    """viser, or one line naming the extra that installs it."""
    try:
        import viser
    except ImportError:
        raise OccDataError("occdata view needs viser, which is not installed: pip install 'fastocc[view]' "
                           "(in a clone: pip install -e '.[view]')") from None
    return viser


def _start_server(viser: ModuleType, host: str, port: int) -> Any:
    try:
        return viser.ViserServer(host=host, port=port, verbose=False)
    except OSError as exc:
        raise OccDataError(f"cannot serve on {host}:{port}: {exc.strerror or exc}") from None


def serve(cfg: ViewConfig, echo: Echo = print, warn: Echo = print) -> None:
    """Serve the viewer until interrupted (Ctrl-C, or SIGTERM as SystemExit); prints its URL."""
    from occdata.view.app import LiveViewer

    viser = import_viser()
    source = ViewSource(cfg.store, cfg.pred, cfg.split)
    if cfg.scene is not None:
        source.scene(cfg.scene)  # an unknown scene is one line before anything starts
    reason = source.empty_reason()
    if reason:
        warn(f"warning: {reason} The page will say so.")
    if cfg.exposed:
        warn(f"warning: --host {cfg.host} serves this store's images, labels and predictions to every machine "
             f"that can reach this one on port {cfg.port or 'chosen below'}; there is no password")
    server = _start_server(viser, cfg.host, cfg.port)
    viewer = None
    try:
        viewer = LiveViewer(server, source, cfg)
        host = cfg.host if ":" not in cfg.host else f"[{cfg.host}]"
        echo(f"occdata view: http://{host}:{server.get_port()} (Ctrl-C to stop)")
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        echo("occdata view: stopped")
    finally:
        if viewer is not None:
            viewer.close()
        server.stop()


@dataclass(frozen=True)
class ExportReport:
    path: Path
    scene: str
    n_keyframes: int
    n_bytes: int


def _classes_in(source: ViewSource, scene: SceneEntry) -> list[int]:
    """Classes (0..16) that occur in the labels or predictions of the scene's keyframes."""
    seen = np.zeros(N_SEMANTIC + 1, dtype=bool)
    for pos in range(len(scene.indices)):
        s = source.sample(scene, pos)
        for grid in (s.semantics, s.pred):
            if grid is not None:
                seen[np.minimum(np.unique(grid), N_SEMANTIC)] = True
    return [c for c in range(N_SEMANTIC) if seen[c]]


def _record(server: Any, source: ViewSource, scene: SceneEntry, cfg: ViewConfig) -> str:
    """Record every keyframe of `scene` (`cfg.seconds_per_keyframe` each) and return the HTML document."""
    opts = cfg.frame
    server.scene.set_up_direction("+z")
    server.initial_camera.position, server.initial_camera.look_at = (-38.0, 0.0, 26.0), (8.0, 0.0, 0.0)
    server.initial_camera.up = (0.0, 0.0, 1.0)
    serializer = server.get_scene_serializer()
    side = SIDE_OFFSET_M if opts.view == "side" else 0.0
    add_legend_plane(server.scene, _classes_in(source, scene), position=(0.0, -46.0 - side, 0.0))
    drawer = SceneDrawer(server.scene)
    for pos in range(len(scene.indices)):
        sample = source.sample(scene, pos, images=opts.cameras, points=opts.lidar, flow=opts.view == "speed")
        frame = compose_frame(sample, opts)
        drawer.draw(sample, frame, opts)
        caption = f"{scene.name} ({scene.split}) · keyframe {pos + 1}/{len(scene.indices)} · {sample.token[:12]}"
        if frame.notes:
            caption += " · " + " ".join(frame.notes)
        server.scene.add_label("/caption", caption, position=(44.0, 0.0, 10.0), font_screen_scale=1.1)
        serializer.insert_sleep(cfg.seconds_per_keyframe)
    return serializer.as_html(dark_mode=True)


def export_html(cfg: ViewConfig) -> ExportReport:
    """Write `cfg.export`: one HTML file (viser's client with the recorded scene inlined) that plays the
    chosen scene's keyframes in a browser with no server and no network."""
    assert cfg.export is not None
    viser = import_viser()
    source = ViewSource(cfg.store, cfg.pred, cfg.split)
    reason = source.empty_reason()
    if reason:
        raise OccDataError(f"nothing to export: {reason}")
    scene = source.scene(cfg.scene) if cfg.scene is not None else source.scenes[0]
    server = _start_server(viser, "127.0.0.1", 0)
    try:
        text = _record(server, source, scene, cfg)
    finally:
        server.stop()
    data = text.encode("utf-8")
    write_atomic(cfg.export, data)
    return ExportReport(path=cfg.export, scene=scene.name, n_keyframes=len(scene.indices), n_bytes=len(data))


def run_view(cfg: ViewConfig, echo: Echo = print, warn: Echo = print) -> None:
    """`occdata view`: the export when `cfg.export` is set, else the live viewer."""
    if cfg.export is None:
        serve(cfg, echo, warn)
        return
    report = export_html(cfg)
    echo(f"wrote {report.path}: {report.scene}, {report.n_keyframes} keyframes, "
         f"{report.n_bytes / 2**20:.1f} MiB; open it in a browser (no server, no install needed)")
