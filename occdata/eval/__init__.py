"""Scoring: Occ3D mIoU and RayIoU (`metrics`), prediction files against a store (`evaluate`), the
image-free baseline (`baseline`), and a store sample's ray origins (`rays`). No torch.

`occdata.metrics` and `occdata.evaluate` moved here (docs/CHANGELOG.md lists every move)."""
