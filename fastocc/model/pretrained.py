"""Backbone weights from a torchvision ResNet state dict or an mmdet / mmdet3d checkpoint (e.g. FCOS3D's).

Both use the same ResNet parameter names below a prefix: torchvision none (`conv1.weight`,
`layer1.0.conv1.weight`, `fc.weight`), mmdet `backbone.` and mmdet3d's multi-modal detectors `img_backbone.`
inside the checkpoint's `state_dict` (a DDP run adds `module.`). The prefix is found from where
`layer1.0.conv1.weight` sits, so any of these loads without renaming rules per source.

mmdet's caffe-style ResNets (FCOS3D's: `style='caffe'` in the checkpoint's own config) were trained on BGR
pixels minus the mean, unit std; our loader gives RGB ImageNet-normalised images. The first conv is linear
and the two conventions share the mean, so its weight is converted exactly: channels reversed and scaled by
our std (zero padding is the mean pixel in both). The caffe style's stride on the 1x1 conv of a bottleneck
(ours: on the 3x3) cannot be converted: those weights load into torchvision's layout as an initialisation.

Keys that need no counterpart: `fc.*` (ImageNet classifier, unused in forward; mmdet has none) and
`num_batches_tracked` (old torchvision files predate it). The deformable convs (DCNv2) of FCOS3D's ResNet-101
keep their 3x3 weight under `conv2.weight`, which loads; their offset branches `conv2.conv_offset.*` have no
counterpart in our plain convs and are reported (a warning) and skipped. Any other missing or extra key, or a
shape mismatch, is one error line naming them.
"""

from __future__ import annotations

import pickle
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from occdata.errors import OccDataError, OccDataWarning
from occdata.sensors.image_ops import IMAGENET_STD

__all__ = ["BackboneMatch", "abbreviate", "backbone_state", "caffe_stem_to_rgb", "is_caffe_style", "load_backbone",
           "match_backbone", "read_weights"]

_ANCHOR = "layer1.0.conv1.weight"  # present in every ResNet of torchvision's and mmdet's layout
_DCN_OFFSET = ".conv_offset."
_CONTAINERS = ("state_dict", "model", "module")  # mmdet/mmdet3d, ours and others, DeepSpeed-like


@dataclass(frozen=True)
class BackboneMatch:
    """How a source state dict (prefix already stripped) lines up with our backbone's keys."""

    loaded: dict[str, Tensor]  # our key -> tensor to copy
    missing: tuple[str, ...]  # ours, required, absent from the source
    extra: tuple[str, ...]  # the source's, no counterpart (DCN offsets excluded)
    dcn_offsets: tuple[str, ...]  # the source's `*.conv_offset.*`: skipped with a warning
    mismatched: tuple[str, ...]  # "key (source shape vs ours)"


def abbreviate(keys: tuple[str, ...] | list[str], first: int = 4) -> str:
    """`"3: a, b, c"` or `"40: a, b, c, d, ..."` (the count and the first few, for one line)."""
    shown = ", ".join(keys[:first])
    return f"{len(keys)}: {shown}{', ...' if len(keys) > first else ''}"


def read_weights(path: str | Path) -> tuple[dict[str, Tensor], str]:
    """The tensors of a weights file and the config text it carries (mmdet's `meta.config` / `meta.cfg`; ""
    if none): a bare state dict, or the `state_dict` (mmdet) / `model` entry of a checkpoint dict. Read with
    `weights_only=True`; anything else is one error line."""
    path = Path(path)
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - a foreign file fails anywhere in the unpickler: one line
        raise OccDataError(f"--pretrained {path}: {_load_failure(exc)}") from None
    meta = obj.get("meta") if isinstance(obj, dict) else None
    config = next((meta[k] for k in ("config", "cfg") if isinstance(meta, dict) and isinstance(meta.get(k), str)), "")
    if isinstance(obj, dict):
        for name in _CONTAINERS:
            inner = obj.get(name)
            if isinstance(inner, dict) and any(isinstance(v, Tensor) for v in inner.values()):
                obj = inner
                break
    if not isinstance(obj, dict) or not any(isinstance(v, Tensor) for v in obj.values()):
        raise OccDataError(f"--pretrained {path}: holds no state dict of tensors (found {type(obj).__name__})")
    return {str(k): v for k, v in obj.items() if isinstance(v, Tensor)}, config


def is_caffe_style(config: str) -> bool:
    """Whether an mmdet config text builds its ResNet caffe-style (`style='caffe'` / `style="caffe"`)."""
    return re.search(r"""style\s*=\s*['"]caffe['"]""", config) is not None


def caffe_stem_to_rgb(weight: Tensor, std_rgb: tuple[float, ...] = IMAGENET_STD) -> Tensor:
    """The first conv `(C, 3, k, k)` of a net fed BGR pixels minus the mean, for RGB (pixels - mean) / std:
    x_bgr[k] = std[2 - k] x_rgb[2 - k], so W_rgb[:, c] = W_bgr[:, 2 - c] std[c]."""
    return weight.flip(1) * torch.tensor(std_rgb, dtype=weight.dtype).view(1, 3, 1, 1)


def _load_failure(exc: Exception) -> str:
    """Why `torch.load(weights_only=True)` refused a file, in a few words."""
    text = str(exc)
    if isinstance(exc, pickle.UnpicklingError) and "Weights only load failed" in text:
        why = next((ln.split("error:", 1)[1].strip() for ln in text.splitlines() if "WeightsUnpickler error:" in ln),
                   "unsupported content")
        return (f"not readable with weights_only=True ({why[:160]}); save its state_dict alone with torch.save "
                "on a machine you trust")
    return f"not a torch weights file ({type(exc).__name__}: {text.strip()[:120]})"


def backbone_state(state: dict[str, Tensor], source: str = "weights") -> tuple[str, dict[str, Tensor]]:
    """The ResNet part of `state` with its prefix (`''`, `backbone.`, `img_backbone.`, `module.backbone.`, ...)
    stripped: `(prefix, state)`. No ResNet or two of them (ambiguous) is one error line."""
    prefixes = sorted({k[: -len(_ANCHOR)] for k in state if k.endswith(_ANCHOR)})
    prefixes = [p for p in prefixes if p == "" or p.endswith(".")]
    if not prefixes:
        raise OccDataError(f"{source}: no ResNet keys (no '{_ANCHOR}' under any prefix; first keys "
                           f"{abbreviate(sorted(state), 3)})")
    if len(prefixes) > 1:
        raise OccDataError(f"{source}: several ResNets ({', '.join(repr(p) for p in prefixes)}); save the one "
                           "to load alone")
    prefix = prefixes[0]
    return prefix, {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def _optional(key: str) -> bool:
    """Ours, may be absent: the unused classifier and the BN step counter."""
    return key.startswith("fc.") or key.endswith("num_batches_tracked")


def match_backbone(ours: dict[str, Tensor], source: dict[str, Tensor]) -> BackboneMatch:
    """Line `source` (ResNet keys, prefix stripped) up with `ours` (our backbone's state dict)."""
    loaded, mismatched = {}, []
    for key, value in source.items():
        if key in ours:
            if tuple(value.shape) == tuple(ours[key].shape):
                loaded[key] = value
            else:
                mismatched.append(f"{key} ({tuple(value.shape)} vs {tuple(ours[key].shape)})")
    missing = tuple(k for k in ours if k not in source and not _optional(k))
    unmatched = [k for k in source if k not in ours]
    dcn = tuple(k for k in unmatched if _DCN_OFFSET in k)
    extra = tuple(k for k in unmatched if _DCN_OFFSET not in k)
    return BackboneMatch(loaded, missing, extra, dcn, tuple(mismatched))


def load_backbone(backbone: nn.Module, path: str | Path) -> str:
    """Copy a weights file's ResNet into `backbone`; returns one line saying what was loaded from where.

    Missing, extra or mis-shaped keys: one `OccDataError` line naming them (nothing is copied). DCN offset
    branches: one `OccDataWarning` line, the rest loads."""
    path = Path(path)
    tensors, config = read_weights(path)
    prefix, source = backbone_state(tensors, f"--pretrained {path}")
    caffe = is_caffe_style(config) and "conv1.weight" in source
    if caffe:
        source["conv1.weight"] = caffe_stem_to_rgb(source["conv1.weight"])
    match = match_backbone(backbone.state_dict(), source)
    problems = [f"{what} {abbreviate(list(keys))}" for what, keys in
                (("missing", match.missing), ("extra", match.extra), ("wrong shape", match.mismatched)) if keys]
    if problems:
        hint = " (a deep-stem ResNetV1c/d? only the 7x7 conv1 stem loads)" if any(
            k.startswith("stem.") for k in match.extra) else ""
        raise OccDataError(f"--pretrained {path} (keys under {prefix or 'no prefix'!r}) does not fit the "
                           f"backbone: {'; '.join(problems)}{hint}")
    if match.dcn_offsets:
        warnings.warn(f"--pretrained {path}: {len(match.dcn_offsets)} deformable-conv offset tensors have no "
                      f"counterpart in our plain 3x3 convs and are skipped "
                      f"({abbreviate(list(match.dcn_offsets), 2)}); their conv weights load", OccDataWarning,
                      stacklevel=2)
    backbone.load_state_dict(match.loaded, strict=False)
    note = "; caffe-style: conv1 converted from BGR minus mean to RGB ImageNet-normalised input" if caffe else ""
    return f"backbone: {len(match.loaded)} tensors from {path.name} (keys under {prefix or 'no prefix'!r}){note}"
