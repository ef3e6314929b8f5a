"""`fastocc`: train, evaluate and benchmark the FastOcc network (torch side)."""

from __future__ import annotations

import click

__all__ = ["main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fastocc")
def main() -> None:
    """FastOcc: camera-only 3D semantic occupancy prediction in pure PyTorch.

    Reads stores written by `occdata build`. Every sub-command has its own --help.
    """


if __name__ == "__main__":
    main()
