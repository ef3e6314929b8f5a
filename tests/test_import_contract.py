"""The import contract: the stages' arrows point one way (docs/architecture.md).

Every `import` in occdata, fastocc and cli (function-level and relative ones included) is read with
`ast`, so a lazy import cannot hide a reverse arrow. occdata: read (nuscenes) -> labels / store (build)
-> eval / view; formats (the label files), runtime and sensors serve them; the store's core never
imports its commands (`store/commands/`); occdata never imports torch, fastocc or cli. fastocc: dist,
model and losses at the bottom, then data, then infer, then train (train may import infer, never the
reverse). Nothing imports cli.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# Modules any stage of the package may import (the package itself: `from occdata import fileio` names fileio).
SHARED: dict[str, set[str]] = {"occdata": {"constants", "errors", "geometry", "fileio", "text"}, "fastocc": set()}
# What each stage may import besides the shared modules and itself.
ALLOWED: dict[str, dict[str, set[str]]] = {
    "occdata": {
        "__init__": set(),
        "constants": set(), "errors": set(), "geometry": set(), "fileio": set(), "text": set(),
        "formats": set(),
        "nuscenes": set(),
        "sensors": set(),
        "runtime": set(),
        "visibility": {"sensors", "nuscenes", "formats"},
        "synth": {"nuscenes", "sensors", "visibility", "formats"},
        "labels": {"nuscenes", "sensors", "visibility", "runtime", "formats"},
        "store": {"nuscenes", "sensors", "visibility", "runtime", "formats"},
        "eval": {"store", "formats"},
        "view": {"store", "eval", "sensors", "visibility", "formats"},
    },
    "fastocc": {
        "__init__": {"deploy"},  # the lazy `fastocc.Predictor`
        "_worker_signals": set(),
        "dist": set(),
        "model": set(),
        "losses": set(),
        "checkpoint": {"model"},
        "storegrid": {"model"},
        "data": {"model", "_worker_signals"},  # workers ignore the job's stop signals
        "infer": {"checkpoint", "data", "dist", "model", "storegrid"},
        "train": {"checkpoint", "data", "dist", "infer", "losses", "model", "storegrid"},
        "deploy": {"checkpoint", "data", "model", "storegrid"},
        "bench": {"deploy", "losses", "model"},
    },
}
FORBIDDEN_IN_OCCDATA = ("torch", "torchvision", "fastocc", "cli")
STORE_COMMANDS = "occdata.store.commands"  # only the commands themselves (and fastocc, cli) import them


def _imports(path: Path, root: Path) -> list[tuple[int, str]]:
    """`(line, dotted name)` of every import in `path` (a file under `root`). `from a import b` gives
    `a.b` (b may be a submodule); a relative import is resolved against the file's package."""
    package = list(path.relative_to(root).parent.parts)
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package[: len(package) - (node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            out += [(node.lineno, f"{base}.{a.name}") for a in node.names]
    return out


def _stage(path: Path, root: Path) -> tuple[str, str]:
    """`(package, stage)` of a file: `occdata/store/build.py` -> ("occdata", "store"), `fastocc/dist.py`
    -> ("fastocc", "dist")."""
    parts = path.relative_to(root).with_suffix("").parts
    return parts[0], parts[1]


def violations(root: Path) -> list[str]:
    """Every import in `root`'s occdata and fastocc that breaks the contract, one line each."""
    bad = []
    for package in ("occdata", "fastocc"):
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root)
            pkg, own = _stage(path, root)
            in_commands = rel.as_posix().startswith(STORE_COMMANDS.replace(".", "/") + "/")
            for line, mod in _imports(path, root):
                parts = mod.split(".")
                if pkg == "occdata" and parts[0] in FORBIDDEN_IN_OCCDATA:
                    bad.append(f"{rel}:{line} imports {mod} (occdata stays torch-free and below fastocc/cli)")
                    continue
                if parts[0] != pkg or len(parts) < 2:
                    continue
                target = parts[1]
                if target not in ALLOWED[pkg]:
                    continue  # `from fastocc import Predictor`: a name of the package itself, not a stage
                if target != own and target not in SHARED[pkg] and target not in ALLOWED[pkg][own]:
                    bad.append(f"{rel}:{line}: {own} imports {mod} ({target} is not below {own})")
                elif pkg == "occdata" and mod.startswith(STORE_COMMANDS + ".") and not in_commands:
                    bad.append(f"{rel}:{line}: {own} imports {mod} (the store's commands sit above its core)")
    return bad


def _stages(root: Path, package: str) -> set[str]:
    return {_stage(p, root)[1] for p in (root / package).rglob("*.py")}


@pytest.mark.parametrize("package", ["occdata", "fastocc"])
def test_every_stage_is_listed(package: str) -> None:
    stages = _stages(REPO, package)
    assert stages == set(ALLOWED[package]), f"stage(s) without a rule: {sorted(stages ^ set(ALLOWED[package]))}"


def test_stages_import_one_way() -> None:
    bad = violations(REPO)
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("package", ["occdata", "fastocc", "benchmarks"])
def test_nothing_imports_cli(package: str) -> None:
    bad = [f"{p.relative_to(REPO)}:{line} imports {mod}" for p in sorted((REPO / package).rglob("*.py"))
           for line, mod in _imports(p, REPO) if mod.split(".")[0] == "cli"]
    assert not bad, "\n".join(bad)


def test_the_contract_catches_planted_reverse_arrows(tmp_path: Path) -> None:
    """The real checker on a planted tree: each reverse arrow (absolute, relative, function-level) is
    reported with its line, and the allowed imports beside them are not."""
    files = {
        "occdata/store/core.py": "from ..formats.gridspec import GridSpec\n"  # allowed: formats is below store
                                 "from .commands import info\n",  # the core importing a command
        "occdata/store/commands/cmd.py": "from ..labelgrid import store_grid\n",  # allowed: a command uses the core
        "occdata/eval/score.py": "from occdata.store.reader import StoreReader\n",  # allowed
        "occdata/formats/files.py": "def f():\n    from ..labels import scene\n",  # formats above labels
        "occdata/nuscenes/read.py": "import torch\n",
        "fastocc/infer/run.py": "from fastocc import dist\n"  # allowed
                                "def f():\n    from ..train import loop\n",  # infer above train
        "fastocc/train/loop.py": "from fastocc.infer import evaluate\n",  # allowed: train above infer
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    assert [b.split(" (")[0] for b in violations(tmp_path)] == [
        "occdata/formats/files.py:2: formats imports occdata.labels.scene",
        "occdata/nuscenes/read.py:1 imports torch",
        "occdata/store/core.py:2: store imports occdata.store.commands.info",
        "fastocc/infer/run.py:3: infer imports fastocc.train.loop",
    ]
