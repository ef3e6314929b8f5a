"""The live viewer: a viser server with a control panel (scene, timeline, play, view, mask, style, layers,
classes) and one drawing thread that always draws the latest request.

Switch time: every request is timed from the moment the server receives it to the moment the browser
that asked has drawn the new scene (viser's `get_render` round trip: the browser applies the scene
messages, commits them and renders a frame before it answers). The status line shows it.
"""

from __future__ import annotations

import dataclasses
import html
import threading
import time
from dataclasses import dataclass
from typing import Any

from occdata.constants import CLASS_COLORS, CLASS_NAMES
from occdata.view.config import MASK_CHOICES, STYLES, VIEWS, FrameOptions, ViewConfig
from occdata.view.draw import SceneDrawer
from occdata.view.frame import SIDE_OFFSET_M, compose_frame
from occdata.view.source import MASK_ARRAYS, SampleData, SceneEntry, ViewSource
from occdata.view.voxels import (
    ERROR_COLORS,
    ERROR_KINDS,
    GHOST_COLOR,
    N_SEMANTIC,
    SPEED_COLORS,
    STATIC_COLOR,
    speed_bin_name,
)

__all__ = ["LiveViewer", "Request"]

_PLAY_SECONDS = 0.5  # keyframes are 2 Hz: play in real time (slower when drawing takes longer)
_CAMERA_PRESETS = {  # name -> (position, look_at, up) in key ego
    "behind": ((-38.0, 0.0, 26.0), (8.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "top": ((0.0, 0.0, 105.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
}


@dataclass(frozen=True)
class Request:
    """What the user asked to see: a keyframe `position` of `scene` drawn with `options`."""

    scene: str
    position: int
    options: FrameOptions


def _swatch(rgb: tuple[int, int, int], text: str) -> str:
    r, g, b = rgb
    return (f'<div style="display:flex;align-items:center;gap:6px;margin:1px 0"><span style="display:inline-block;'
            f'width:14px;height:14px;border:1px solid #888;background:rgb({r},{g},{b})"></span>'
            f'<span>{html.escape(text)}</span></div>')


class LiveViewer:
    """The control panel and drawing loop on one viser server (shared by every connected browser)."""

    def __init__(self, server: Any, source: ViewSource, cfg: ViewConfig) -> None:
        self.server, self.source, self.cfg = server, source, cfg
        self.drawer = SceneDrawer(server.scene)
        self.timings_ms: list[float] = []  # request -> drawn, per drawn request
        self._cv = threading.Condition()
        self._want: tuple[Request, float, Any] | None = None
        self._drawn: Request | None = None
        self._sample: SampleData | None = None
        self._stop = threading.Event()
        self._playing = threading.Event()
        self._drawn_event = threading.Event()
        self._setup_scene()
        self._build_gui()
        self._threads = [threading.Thread(target=self._draw_loop, name="occdata-view-draw", daemon=True),
                         threading.Thread(target=self._play_loop, name="occdata-view-play", daemon=True)]
        for t in self._threads:
            t.start()
        if source.scenes:
            self.request()

    # --- set-up -----------------------------------------------------------------------------------------
    def _setup_scene(self) -> None:
        s = self.server
        s.scene.set_up_direction("+z")
        pos, look, up = _CAMERA_PRESETS["behind"]
        s.initial_camera.position, s.initial_camera.look_at, s.initial_camera.up = pos, look, up
        s.gui.configure_theme(dark_mode=True, show_share_button=False, control_width="medium")
        s.gui.set_panel_label("occdata view")

    def _build_gui(self) -> None:
        gui, src, frame = self.server.gui, self.source, self.cfg.frame
        self.status = gui.add_markdown("loading ...")
        self.notes = gui.add_markdown("")
        reason = src.empty_reason()
        if reason:
            self.notes.content = f"**{reason}**"
            self.server.scene.add_label("/note", reason, position=(0.0, 0.0, 4.0), font_screen_scale=1.3,
                                       anchor="bottom-center")
            self.status.content = "nothing to draw"
            return
        first = src.scene(self.cfg.scene) if self.cfg.scene else src.scenes[0]
        self.scene_dd = gui.add_dropdown("Scene", [s.title for s in src.scenes], initial_value=first.title)
        self.slider = gui.add_slider("Keyframe", min=1, max=len(first.indices), step=1, initial_value=1)
        self.play = gui.add_button("Play")
        self.step = gui.add_button_group("Step", ("previous", "next"))
        views = [VIEWS[v] for v in VIEWS
                 if v == "label" or (v == "speed" and src.has_flow) or (v != "speed" and src.has_pred_folder)]
        self.view_dd = gui.add_dropdown("View", views, initial_value=VIEWS[frame.view])
        self.mask_dd = gui.add_dropdown("Mask", self._mask_choices(), initial_value=frame.mask)
        self.outside_cb = gui.add_checkbox("Voxels outside the mask (grey)", frame.outside_mask)
        self.style_dd = gui.add_dropdown("Style", list(STYLES.values()), initial_value=STYLES[frame.style])
        self.camera_bg = gui.add_button_group("Look from", tuple(_CAMERA_PRESETS))
        with gui.add_folder("Layers"):
            self.ego_cb = gui.add_checkbox("Ego car", frame.ego)
            self.cameras_cb = gui.add_checkbox("Cameras (frustums with images)", frame.cameras)
            self.panels_cb = gui.add_checkbox("Camera images as panels", False)
            self.lidar_cb = gui.add_checkbox("LiDAR points (stored depth points)", frame.lidar)
        with gui.add_folder("Classes"):
            self.legend = gui.add_html("")
            self.all_bg = gui.add_button_group("Show", ("all", "none"))
            self.class_cb = [gui.add_checkbox(CLASS_NAMES[c], c not in frame.hidden) for c in range(N_SEMANTIC)]
        self.panels_folder = gui.add_folder("Camera images", visible=False)
        self.panels: list[Any] = []
        self._connect()

    def _mask_choices(self) -> list[str]:
        present = {flag for flag in ("labels/present", "visibility/present")
                   if bool(self.source.reader.small(flag).any())}
        return [m for m in MASK_CHOICES if m == "none" or MASK_ARRAYS[m][1] in present]

    def _connect(self) -> None:
        for h in (self.view_dd, self.mask_dd, self.outside_cb, self.style_dd, self.ego_cb, self.cameras_cb,
                  self.lidar_cb, self.panels_cb, self.slider, *self.class_cb):
            h.on_update(lambda ev: self.request(ev.client))
        self.scene_dd.on_update(self._on_scene)
        self.play.on_click(lambda _: self._toggle_play())
        self.step.on_click(lambda ev: self._step(1 if ev.target.value == "next" else -1))
        self.all_bg.on_click(self._on_all)
        self.camera_bg.on_click(lambda ev: self._look(ev.target.value))
        self.server.on_client_connect(lambda client: self.request(client))

    # --- GUI events -------------------------------------------------------------------------------------
    def _scene_entry(self) -> SceneEntry:
        return next(s for s in self.source.scenes if s.title == self.scene_dd.value)

    def _on_scene(self, ev: Any) -> None:
        n = len(self._scene_entry().indices)
        self.slider.max = n
        if int(self.slider.value) > n or int(self.slider.value) == 1:
            self.slider.value = 1
            self.request(ev.client)
        else:
            self.slider.value = 1  # its callback requests the draw

    def _step(self, delta: int) -> None:
        n = len(self._scene_entry().indices)
        self.slider.value = (int(self.slider.value) - 1 + delta) % n + 1

    def _toggle_play(self) -> None:
        if self._playing.is_set():
            self._playing.clear()
            self.play.label = "Play"
        else:
            self._playing.set()
            self.play.label = "Pause"

    def _on_all(self, ev: Any) -> None:
        for cb in self.class_cb:
            cb.value = ev.target.value == "all"

    def _look(self, preset: str) -> None:
        pos, look, up = _CAMERA_PRESETS[preset]
        if preset == "top" and self.view_dd.value == VIEWS["side"]:
            pos = (pos[0], pos[1], pos[2] + SIDE_OFFSET_M * 1.5)
        for client in self.server.get_clients().values():
            client.camera.position, client.camera.look_at, client.camera.up_direction = pos, look, up

    def current(self) -> Request:
        """The request that the control panel describes now."""
        view = next(k for k, v in VIEWS.items() if v == self.view_dd.value)
        style = next(k for k, v in STYLES.items() if v == self.style_dd.value)
        options = FrameOptions(view=view, mask=self.mask_dd.value, outside_mask=self.outside_cb.value,  # type: ignore[arg-type]
                               style=style, ego=self.ego_cb.value, cameras=self.cameras_cb.value,  # type: ignore[arg-type]
                               lidar=self.lidar_cb.value,
                               hidden=frozenset(c for c, cb in enumerate(self.class_cb) if not cb.value))
        return Request(scene=self._scene_entry().name, position=int(self.slider.value) - 1, options=options)

    def request(self, client: Any = None) -> None:
        """Ask the drawing thread for what the control panel shows (the latest request wins)."""
        with self._cv:
            self._want = (self.current(), time.perf_counter(), client)
            self._drawn_event.clear()
            self._cv.notify()

    # --- drawing ----------------------------------------------------------------------------------------
    def _draw_loop(self) -> None:
        while not self._stop.is_set():
            with self._cv:
                while self._want is None and not self._stop.is_set():
                    self._cv.wait(timeout=0.5)
                if self._stop.is_set():
                    return
                req, t0, client = self._want  # type: ignore[misc]
                self._want = None
            try:
                self._draw(req, t0, client)
            except Exception as exc:  # noqa: BLE001 - shown in the page, the server keeps running
                where = f"{req.scene} keyframe {req.position + 1}"
                self.notes.content = f"**Could not draw {where}:** {html.escape(str(exc))}"
            self._drawn_event.set()

    def _load(self, req: Request) -> SampleData:
        """The requested keyframe, reused while only the drawing options change."""
        o, s = req.options, self._sample
        images, points, flow = o.cameras or bool(self.panels_cb.value), o.lidar, o.view == "speed"
        if (s is None or (s.scene, s.position) != (req.scene, req.position)
                or (images and s.images is None) or (points and s.points_ego is None)
                or (flow and s.flow is None and self.source.has_flow)):
            s = self.source.sample(self.source.scene(req.scene), req.position, images=images, points=points,
                                   flow=flow)
        self._sample = s
        return s

    def _draw(self, req: Request, t0: float, client: Any) -> None:
        last, sample = self._drawn, self._load(req)
        same_drawing = (last is not None and (last.scene, last.position) == (req.scene, req.position)
                        and dataclasses.replace(last.options, hidden=req.options.hidden) == req.options)
        if same_drawing:  # class toggles, a new browser: no new geometry
            self.drawer.set_hidden(req.options.hidden)
        else:
            frame = compose_frame(sample, req.options)
            with self.server.atomic():
                self.drawer.draw(sample, frame, req.options)
            self._update_text(frame, req)
        self._drawn = req
        self._update_panels(sample)
        self._update_status(sample, req.options, self._time_drawn(t0, client))

    def _time_drawn(self, t0: float, client: Any) -> float | None:
        """Milliseconds from the request to the asking browser having rendered it (None: no browser)."""
        clients = self.server.get_clients()
        target = client if client is not None else next(iter(clients.values()), None)
        if target is None:
            return None
        try:
            target.get_render(height=32, width=32, timeout=20.0)
        except Exception:  # noqa: BLE001 - the browser went away or is too slow: no figure
            return None
        ms = 1000.0 * (time.perf_counter() - t0)
        self.timings_ms.append(ms)
        return ms

    def _update_panels(self, sample: SampleData) -> None:
        show = bool(self.panels_cb.value)
        self.panels_folder.visible = show
        if not show:
            return
        with self.panels_folder:
            for k, img in enumerate(sample.images or ()):
                if k < len(self.panels):
                    self.panels[k].image = img
                else:
                    self.panels.append(self.server.gui.add_image(img, label=sample.camera_names[k], format="jpeg",
                                                                 jpeg_quality=80))

    def _update_text(self, frame: Any, req: Request) -> None:
        self.notes.content = "  \n".join(f"**{n}**" for n in frame.notes)
        rows = []
        if req.options.view == "error":
            rows += [_swatch(ERROR_COLORS[k], kind) for k, kind in enumerate(ERROR_KINDS)]
        if req.options.view == "speed":
            rows += [_swatch(SPEED_COLORS[k - 1] if k else STATIC_COLOR, speed_bin_name(k))
                     for k in range(len(SPEED_COLORS) + 1)]
        present = sorted({layer.class_id for g in frame.groups for layer in g.layers if layer.class_id is not None})
        if req.options.view not in ("error", "speed"):
            rows += [_swatch(CLASS_COLORS[c], CLASS_NAMES[c]) for c in present]
        if any(layer.ghost for g in frame.groups for layer in g.layers):
            rows.append(_swatch(GHOST_COLOR, f"outside the {req.options.mask} mask"))
        self.legend.content = "".join(rows) or "<i>no voxels drawn</i>"

    def _update_status(self, sample: SampleData, options: FrameOptions, ms: float | None) -> None:
        view = VIEWS[options.view].split(" (")[0]
        mask = f" · mask {options.mask}" if options.mask != "none" else ""
        drawn = f" · drawn in {ms:.0f} ms" if ms is not None else ""
        self.status.content = (f"**{sample.scene}** · keyframe {sample.position + 1}/{sample.n_in_scene} · "
                               f"{view} view{mask} · sample {sample.token[:12]}{drawn}")

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            if not self._playing.wait(timeout=0.2):
                continue
            t = time.perf_counter()
            self._step(1)
            self._drawn_event.wait(timeout=30.0)
            time.sleep(max(0.0, _PLAY_SECONDS - (time.perf_counter() - t)))

    def close(self) -> None:
        """Stop the drawing and playing threads."""
        self._stop.set()
        self._playing.clear()
        with self._cv:
            self._cv.notify_all()
        for t in self._threads:
            t.join(timeout=5.0)
