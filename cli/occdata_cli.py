"""`occdata`: turn nuScenes-format data (+ Occ3D labels) into one chunked zarr store (no torch)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from cli._common import friendly_errors

__all__ = ["main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fastocc")
def main() -> None:
    """occdata: nuScenes-format data and Occ3D labels -> one chunked zarr store.

    Every sub-command has its own --help.
    """


@main.command()
@click.option("--root", required=True, type=click.Path(path_type=Path), help="nuScenes-format dataset root.")
@click.option("--version", default=None, help="Version folder (v1.0-trainval, v1.0-mini, ...); auto if only one.")
@click.option("--check-files/--no-check-files", default=True, show_default=True,
              help="Check that every keyframe image and LiDAR file exists.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@friendly_errors
def scan(root: Path, version: str | None, check_files: bool, as_json: bool) -> None:
    """Read and validate a nuScenes-format tree; print scenes and samples per split.

    Every foreign key is resolved; a broken tree fails with one line naming the file or token.
    """
    from occdata.nuscenes.summary import scan_tree

    summary = scan_tree(root, version, check_files)
    if as_json:
        click.echo(json.dumps(summary, indent=2))
        return
    click.echo(f"{summary['root']} [{summary['version']}]: {summary['scenes']} scenes, {summary['samples']} samples")
    for split, n in summary["samples_per_split"].items():
        click.echo(f"  {split:>12}: {summary['scenes_per_split'][split]:5d} scenes {n:7d} samples")


if __name__ == "__main__":
    main()
