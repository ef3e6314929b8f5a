"""Digest of what the pipeline writes on a small world: synth, build, labels, eval, and the model.

Run it on two commits and diff the JSON to show a refactor changed no byte:

    python scripts/output_digest.py --work /tmp/d_new --json /tmp/new.json
    (in a checkout of the older commit)  python scripts/output_digest.py --work /tmp/d_old --json /tmp/old.json
    python scripts/output_digest.py --compare /tmp/old.json /tmp/new.json

It drives the commands (`occdata synth/build/labels/eval/baseline`) as a user does, so it needs
nothing but a stable CLI, and hashes every file they write. The zarr store is hashed array by array
(decoded values and attributes) plus its chunk files; `fastocc`'s nano network is hashed on a fixed
seed and fixed inputs (forward pass, one thread).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
# Wall-clock and host facts that legitimately differ between two runs of the same code.
VOLATILE_KEYS = {"created", "finished", "started", "elapsed_s", "wall_s", "host", "hostname", "pid", "date",
                 "time", "timestamp", "duration_s", "seconds", "code_version", "git"}


def _run(*args: str) -> str:
    env = {**os.environ, "PYTHONPATH": str(REPO), "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", *args], cwd=REPO, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
    return proc.stdout


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


_WORK = [""]  # the scratch folder, written as <work> so that two runs in two folders compare equal


def _scrub(obj: Any) -> Any:
    if isinstance(obj, str) and _WORK[0]:
        return obj.replace(_WORK[0], "<work>")
    if isinstance(obj, dict):
        return {k: _scrub(v) for k, v in sorted(obj.items()) if k not in VOLATILE_KEYS}
    if isinstance(obj, list):
        return [_scrub(v) for v in obj]
    return obj


def _file_digest(path: Path) -> str:
    if path.suffix == ".json":
        try:
            return _sha(json.dumps(_scrub(json.loads(path.read_text())), sort_keys=True).encode())
        except ValueError:
            pass
    return _sha(path.read_bytes())


def tree_digest(root: Path, skip: tuple[str, ...] = ()) -> dict[str, str]:
    """`{relative path: sha}` of every file under `root` (JSON files with volatile keys removed)."""
    return {str(p.relative_to(root)): _file_digest(p) for p in sorted(root.rglob("*"))
            if p.is_file() and not any(s in p.parts for s in skip)}


def store_digest(store: Path) -> dict[str, str]:
    """Each array's decoded values and attributes, and the store's root attributes (volatile keys off)."""
    import numpy as np
    import zarr

    root = zarr.open_group(str(store), mode="r")
    out = {"/attrs": _sha(json.dumps(_scrub(dict(root.attrs)), sort_keys=True, default=str).encode())}

    def walk(group: Any, prefix: str) -> None:
        for name, arr in sorted(group.arrays()):
            data = np.asarray(arr[...])
            out[f"{prefix}{name}"] = f"{data.dtype}{data.shape}:{_sha(data.tobytes())}"
        for name, sub in sorted(group.groups()):
            out[f"{prefix}{name}/attrs"] = _sha(json.dumps(_scrub(dict(sub.attrs)), sort_keys=True,
                                                           default=str).encode())
            walk(sub, f"{prefix}{name}/")

    walk(root, "")
    return out


def model_digest() -> dict[str, str]:
    import torch

    from fastocc.model import FastOcc, preset, synthetic_inputs

    torch.set_num_threads(1)
    torch.manual_seed(0)
    cfg = preset("nano")
    net = FastOcc(cfg).eval()
    with torch.no_grad():
        out = net(synthetic_inputs(1, cfg.input_hw, seed=0))
    return {"params": _sha(b"".join(p.detach().numpy().tobytes() for p in net.parameters())),
            "voxel_logits": _sha(out.voxel_logits.numpy().tobytes())}


def digest(work: Path) -> dict[str, Any]:
    work.mkdir(parents=True, exist_ok=True)
    _WORK[0] = str(work)
    world, store, labels = work / "world", work / "data.zarr", work / "gen"
    _run("cli.occdata_cli", "synth", "--out", str(world), "--scenes", "2", "--samples", "4", "--seed", "5",
         "--width", "320", "--height", "180", "--no-progress")
    _run("cli.occdata_cli", "build", "--root", str(world), "--gts", str(world / "gts"), "--out", str(store),
         "--lidar-sweeps", "2", "--block-samples", "3", "--no-progress")
    _run("cli.occdata_cli", "labels", "--root", str(world), "--out", str(labels), "--all-sweeps",
         "--no-progress")
    ev = json.loads(_run("cli.occdata_cli", "eval", "--pred", str(labels), "--store", str(store), "--split", "val",
                         "--json", "--no-progress"))
    base = _run("cli.occdata_cli", "baseline", "--store", str(store))
    return {"synth": tree_digest(world), "store": store_digest(store), "labels": tree_digest(labels),
            "eval": _scrub(ev), "baseline": base.strip().splitlines()[-1], "model": model_digest()}


def compare(a: dict[str, Any], b: dict[str, Any], path: str = "") -> list[str]:
    """Every key whose value differs between two digests (or exists in one only)."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return [] if a == b else [f"{path}: {a!r} != {b!r}"]
    out = []
    for k in sorted(set(a) | set(b)):
        if k not in a or k not in b:
            out.append(f"{path}/{k}: only in {'second' if k not in a else 'first'}")
        else:
            out += compare(a[k], b[k], f"{path}/{k}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, help="scratch folder for the outputs")
    ap.add_argument("--json", type=Path, help="write the digest here")
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="diff two digest files")
    args = ap.parse_args()
    if args.compare:
        diffs = compare(*(json.loads(p.read_text()) for p in args.compare))
        print("\n".join(diffs) if diffs else "identical")
        raise SystemExit(1 if diffs else 0)
    if not args.work or not args.json:
        ap.error("--work and --json are required unless --compare is given")
    d = digest(args.work)
    args.json.write_text(json.dumps(d, indent=1, sort_keys=True))
    print(f"{sum(len(v) for v in d.values() if isinstance(v, dict))} digests -> {args.json}")


if __name__ == "__main__":
    main()
