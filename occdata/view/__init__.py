"""`occdata view`: the store's scenes in 3D in a browser (labels, predictions, error view, masks, cameras,
LiDAR points), live (viser) or as one self-contained HTML file. Optional extra: `pip install 'fastocc[view]'`
(in a clone: `pip install -e '.[view]'`).

Only `run` imports viser (when called); the rest is numpy and the store reader. No torch.
"""

from occdata.view.config import FrameOptions, ViewConfig
from occdata.view.run import ExportReport, export_html, run_view, serve

__all__ = ["ExportReport", "FrameOptions", "ViewConfig", "export_html", "run_view", "serve"]
