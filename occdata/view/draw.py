"""Put a composed `Frame` into a viser scene (a live server's, or one being recorded for the export).

Scene nodes: `/truth/<class>`, `/pred/<class>`, `/error/<kind>/<class>`, `/<group>/outside_mask`,
`/<group>/ego`, `/<group>/title`, `/sensors/cameras/<CAM>`, `/sensors/lidar`, `/note`. A voxel layer is
one point cloud (flat style: screen-facing squares in the exact class colours, unlit) or one batched mesh
of cubes (cubes style: lit, so colours shift with the light); either way one draw call per layer.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from occdata.constants import EGO_SIZE
from occdata.view.config import FrameOptions
from occdata.view.frame import Frame
from occdata.view.render import EGO_COLOR, class_legend
from occdata.view.source import SampleData
from occdata.view.voxels import VoxelLayer

__all__ = ["FLAT_POINT_SIZE", "SceneDrawer", "add_legend_plane", "cube_mesh", "height_colors"]

FLAT_POINT_SIZE = 0.44  # m: a little over the 0.4 m voxel, so that oblique views show no gaps
_CUBE_SIDE = 0.38  # m: a small gap between cubes keeps single voxels readable
_FRUSTUM_COLOR = (255, 200, 40)
_FRUSTUM_SCALE = 2.5
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)


def cube_mesh(side: float = _CUBE_SIDE) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned cube centred at the origin: `vertices (8, 3) float32`, `faces (12, 3) uint32`
    (counter-clockwise seen from outside)."""
    h = side / 2
    v = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)], dtype=np.float32)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    return v, np.array(faces, dtype=np.uint32)


def height_colors(z: np.ndarray, lo: float = -2.0, hi: float = 4.0) -> np.ndarray:
    """`(N, 3) uint8` colours of points by height `z (N,)` (m): the turbo colour map from `lo` to `hi`."""
    t = np.clip((np.asarray(z, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.rint(255 * t).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_TURBO)
    return np.ascontiguousarray(bgr.reshape(-1, 3)[:, ::-1])


def add_legend_plane(scene: Any, classes: list[int], position: tuple[float, float, float]) -> None:
    """The class legend (occdata.view.render's) as a picture lying flat in the scene (for the export, which
    has no control panel), readable from behind the car."""
    img = class_legend(classes, width=220)
    h, w = img.shape[:2]
    width_m = 18.0
    # Image x (right) along -y, image y (down) along -x: read from behind the car, text upright.
    R = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    from occdata.geometry import quaternion_wxyz_from_matrix

    scene.add_image("/legend", img, render_width=width_m, render_height=width_m * h / w, format="png",
                    wxyz=tuple(quaternion_wxyz_from_matrix(R)), position=position, cast_shadow=False,
                    receive_shadow=False)


class SceneDrawer:
    """Draws frames into one viser `SceneApi`, replacing the previous frame's nodes (and removing those
    the new frame does not have). Class toggles only change node visibility (no new geometry)."""

    def __init__(self, scene: Any) -> None:
        self.scene = scene
        self._nodes: dict[str, tuple[Any, int | None]] = {}  # name -> (handle, class for toggles)
        self._cube = cube_mesh()

    def _layer(self, name: str, layer: VoxelLayer, offset: tuple[float, float, float], opts: FrameOptions) -> Any:
        visible = layer.class_id not in opts.hidden
        if opts.style == "flat":
            return self.scene.add_point_cloud(
                name, layer.centers_ego, layer.colors(), point_size=FLAT_POINT_SIZE, point_shape="square",
                point_shading="flat", precision="float16", position=offset, visible=visible)
        n = len(layer.centers_ego)
        return self.scene.add_batched_meshes_simple(
            name, self._cube[0], self._cube[1], np.broadcast_to(_IDENTITY, (n, 4)), layer.centers_ego,
            batched_colors=layer.color, opacity=0.3 if layer.ghost else None, lod="off", cast_shadow=False,
            receive_shadow=False, position=offset, visible=visible)

    def _groups(self, frame: Frame, opts: FrameOptions, new: dict[str, tuple[Any, int | None]]) -> None:
        for group in frame.groups:
            for layer in group.layers:
                name = f"/{group.name}/{layer.name}"
                new[name] = (self._layer(name, layer, group.offset, opts), layer.class_id)
            if opts.ego:
                center = tuple(float(a + b) for a, b in zip(frame.ego_center, group.offset, strict=True))
                new[f"/{group.name}/ego"] = (self.scene.add_box(
                    f"/{group.name}/ego", color=EGO_COLOR, dimensions=EGO_SIZE, position=center,
                    cast_shadow=False, receive_shadow=False), None)
            if len(frame.groups) > 1:
                pos = (42.0 + group.offset[0], group.offset[1], 8.0)
                new[f"/{group.name}/title"] = (self.scene.add_label(
                    f"/{group.name}/title", group.title, position=pos, font_screen_scale=1.3), None)

    def _sensors(self, sample: SampleData, frame: Frame, opts: FrameOptions,
                 new: dict[str, tuple[Any, int | None]]) -> None:
        off = np.asarray(frame.sensor_offset, dtype=np.float64)
        if opts.cameras:
            for k, (cam, name) in enumerate(zip(sample.cameras, sample.camera_names, strict=False)):
                image = sample.images[k] if sample.images is not None and k < len(sample.images) else None
                node = f"/sensors/cameras/{name}"
                new[node] = (self.scene.add_camera_frustum(
                    node, fov=cam.fov_y, aspect=cam.aspect, scale=_FRUSTUM_SCALE, color=_FRUSTUM_COLOR,
                    image=image, format="jpeg", jpeg_quality=80, wxyz=cam.wxyz,
                    position=tuple(np.asarray(cam.position) + off), cast_shadow=False, receive_shadow=False), None)
        if opts.lidar and sample.points_ego is not None and len(sample.points_ego):
            pts = sample.points_ego
            new["/sensors/lidar"] = (self.scene.add_point_cloud(
                "/sensors/lidar", pts, height_colors(pts[:, 2]), point_size=0.12, point_shape="circle",
                point_shading="flat", precision="float16", position=tuple(off)), None)

    def draw(self, sample: SampleData, frame: Frame, opts: FrameOptions) -> None:
        """Replace the scene's content by `frame` (and the sensors of `sample`)."""
        new: dict[str, tuple[Any, int | None]] = {}
        self._groups(frame, opts, new)
        self._sensors(sample, frame, opts, new)
        if not frame.groups and frame.notes:
            new["/note"] = (self.scene.add_label("/note", " ".join(frame.notes), position=(0.0, 0.0, 4.0),
                                                 anchor="bottom-center", font_screen_scale=1.2), None)
        for name in set(self._nodes) - set(new):
            self._nodes[name][0].remove()
        self._nodes = new

    def set_hidden(self, hidden: frozenset[int]) -> None:
        """Show every class layer except those of the classes in `hidden`."""
        for handle, cls in self._nodes.values():
            if cls is not None:
                handle.visible = cls not in hidden

    def clear(self) -> None:
        for handle, _ in self._nodes.values():
            handle.remove()
        self._nodes = {}
