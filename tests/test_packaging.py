"""pyproject.toml: the license is an SPDX expression (a TOML table is deprecated by setuptools >= 77 and
warns on every install), and preparing the package metadata, as `pip install -e .` does, warns about none."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_license_is_an_spdx_string_with_a_setuptools_that_reads_it() -> None:
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert meta["project"]["license"] == "Apache-2.0"
    assert "setuptools>=77" in meta["build-system"]["requires"]


def test_preparing_metadata_does_not_warn_about_the_license(tmp_path: Path) -> None:
    setuptools = pytest.importorskip("setuptools")
    if int(setuptools.__version__.split(".")[0]) < 77:
        pytest.skip(f"setuptools {setuptools.__version__} predates SPDX license strings")
    code = ("import warnings, sys\nwarnings.simplefilter('always')\nfrom setuptools import build_meta\n"
            f"build_meta.prepare_metadata_for_build_editable({str(tmp_path)!r})\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # The one license line allowed: setuptools naming the LICENSE file it adds to the metadata.
    said = (proc.stdout + proc.stderr).lower().replace("adding license file 'license'", "")
    assert "license" not in said.replace("license-expression", ""), proc.stderr
    metadata = next(tmp_path.glob("*.dist-info")) / "METADATA"
    assert "License-Expression: Apache-2.0" in metadata.read_text()
