"""`occdata`: turn nuScenes-format data (+ Occ3D labels) into one chunked zarr store (no torch)."""

from __future__ import annotations

import click

__all__ = ["main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fastocc")
def main() -> None:
    """occdata: nuScenes-format data and Occ3D labels -> one chunked zarr store.

    Every sub-command has its own --help.
    """


if __name__ == "__main__":
    main()
