"""The import contract: the stages' arrows point one way (docs/architecture.md).

Every `import` in occdata, fastocc and cli (function-level ones included) is read with `ast`, so a
lazy import cannot hide a reverse arrow. read (nuscenes) -> labels / store (build) -> eval / view;
runtime and sensors serve them; occdata never imports torch, fastocc or cli; nothing imports cli.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = {"occdata", "constants", "errors", "geometry", "fileio", "formats"}
# What each occdata stage may import besides the shared modules (and itself).
ALLOWED: dict[str, set[str]] = {
    "constants": set(), "errors": set(), "geometry": set(), "fileio": set(), "formats": set(),
    "nuscenes": set(),
    "sensors": set(),
    "runtime": set(),
    "visibility": {"sensors", "nuscenes"},
    "synth": {"nuscenes", "sensors", "visibility"},
    "labels": {"nuscenes", "sensors", "visibility", "runtime"},
    "store": {"nuscenes", "sensors", "visibility", "runtime"},
    "eval": {"store"},
    "view": {"store", "eval", "sensors", "visibility"},
}
FORBIDDEN_IN_OCCDATA = ("torch", "torchvision", "fastocc", "cli")


def _imports(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


def _stage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if parts[0] == "occdata" and len(parts) > 1 else parts[0]


def _files(package: str) -> list[Path]:
    return sorted((REPO / package).rglob("*.py"))


def test_every_occdata_stage_is_listed() -> None:
    stages = {p.stem if p.parent.name == "occdata" else p.relative_to(REPO / "occdata").parts[0]
              for p in _files("occdata")} - {"__init__"}
    assert stages == set(ALLOWED), f"new stage(s) without a rule: {sorted(stages - set(ALLOWED))}"


def test_occdata_stages_import_one_way() -> None:
    bad = []
    for path in _files("occdata"):
        rel = path.relative_to(REPO)
        own = _stage(".".join(rel.with_suffix("").parts))
        for line, mod in _imports(path):
            top = mod.split(".")[0]
            if top in FORBIDDEN_IN_OCCDATA:
                bad.append(f"{rel}:{line} imports {mod} (occdata stays torch-free and below fastocc/cli)")
            elif top == "occdata":
                target = _stage(mod)
                if target not in SHARED and target != own and target not in ALLOWED[own]:
                    bad.append(f"{rel}:{line}: {own} imports {mod} ({target} is not below {own})")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("package", ["occdata", "fastocc", "benchmarks"])
def test_nothing_imports_cli(package: str) -> None:
    bad = [f"{p.relative_to(REPO)}:{line} imports {mod}" for p in _files(package) for line, mod in _imports(p)
           if mod.split(".")[0] == "cli"]
    assert not bad, "\n".join(bad)


def test_the_contract_catches_a_reverse_arrow(tmp_path: Path) -> None:
    """The checker itself: a store module that imports eval is reported (not a test that cannot fail)."""
    f = tmp_path / "x.py"
    f.write_text("def f():\n    from occdata.eval.metrics import MIoUAccumulator\n")
    (line, mod), = _imports(f)
    assert (line, mod) == (2, "occdata.eval.metrics")
    assert _stage(mod) == "eval" and "eval" not in ALLOWED["store"]
