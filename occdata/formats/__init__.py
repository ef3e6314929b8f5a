"""The label formats, one stage below labels/ and store/: what a label grid is (`gridspec`: `GridSpec`
and the benchmarks' presets), each grid's label files (`gridfiles`: layout, writing, reading as the
benchmark's loader does) and the Occ3D label file (`occ3d`). Numpy only; imports only the shared modules.

These were `occdata.grids`, `occdata.gridfiles` and `occdata.occ3d` (docs/CHANGELOG.md lists every move)."""
