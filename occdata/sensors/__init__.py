"""Sensor-side kernels shared by the build and the loader: projection of points into cameras, JPEG
checks, image resizing, LiDAR depth targets. Numba kernels with numpy twins; no torch."""
