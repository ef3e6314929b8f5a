"""Options that several commands share, defined once, and choices read from the configs that own them."""

from __future__ import annotations

import dataclasses
import enum
import functools
import importlib
import os
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
from click.core import ParameterSource

from cli._common import DEFAULT_STORE
from occdata.constants import GRID
from occdata.errors import OccDataError

__all__ = ["JSON_UNITS", "ConfigChoice", "ShownDefault", "cluster_options", "config_choice", "device_option",
           "grid_range_option", "json_option", "progress_option", "removed_option", "renamed_option", "rig_options",
           "root_options", "split_option", "split_source_options", "splits_option", "store_option", "store_split"]

F = TypeVar("F", bound=Callable[..., Any])

ROOT_HELP = "nuScenes-format dataset root (a folder or a file:// URL)."
STORE_HELP = "An occdata zarr store: a folder or an fsspec URL (file://, s3://, ...)."
SPLITS = "train, val, test, mini_train, mini_val, ..."
AUTO_SPLIT = "val, or the store's only split"
JSON_UNITS = "IoUs and other fractions in percent, 0-100, as its 'unit' key says"  # one unit in every --json


class ConfigChoice(click.Choice):  # type: ignore[type-arg]
    """A `click.Choice` whose values come from the config module that defines them (one copy), read on
    first use: those modules import zarr or torch, which starting the CLI and `--help` of a group should
    not pay for."""

    def __init__(self, source: str, extra: tuple[str, ...] = (), case_sensitive: bool = True) -> None:
        # no super().__init__: it would store the choices now
        self.source = source
        self.extra = extra
        self.case_sensitive = case_sensitive
        self._choices: tuple[str, ...] | None = None

    @property  # type: ignore[override]
    def choices(self) -> tuple[str, ...]:
        if self._choices is None:
            self._choices = (*_values(_resolve(self.source)), *self.extra)
        return self._choices


class ShownDefault(click.Option):
    """An option whose --help shows a default described in words (`default_text`) or read from a config
    field (`config_field`, "module:Class.field", read on first use: that module may import torch, which
    --help should not pay for). With `config_field` the option overrides that field: default None = not
    given, so a --config file's value stands."""

    def __init__(self, *args: Any, config_field: str | None = None, default_text: str | None = None,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.config_field = config_field
        self.default_text = default_text

    def get_help_extra(self, ctx: click.Context) -> Any:
        extra = super().get_help_extra(ctx)
        if self.default_text is not None:
            extra["default"] = self.default_text
        elif self.config_field is not None and (value := _field_default(self.config_field)) is not None:
            shown = ("on" if value else "off") if isinstance(value, bool) else f"{value:g}" if isinstance(
                value, float) else str(value)
            extra["default"] = f"{shown}, or the --config file's"
        return extra


def _field_default(source: str) -> Any:
    """The default of the dataclass field `"module:Class.field"`."""
    module_name, _, attr = source.partition(":")
    name, _, field = attr.partition(".")
    cls = getattr(importlib.import_module(module_name), name)
    return next(f.default for f in dataclasses.fields(cls) if f.name == field)


def device_option(config_field: str | None = None) -> Callable[[F], F]:
    """`--device auto|cpu|cuda` (auto = cuda when available, else cpu), default auto; with `config_field`
    the option overrides that config field (default: the field's, auto)."""
    choice = click.Choice(["auto", "cpu", "cuda"])
    help = "auto = cuda when a CUDA device is available, else cpu."
    if config_field is not None:
        return click.option("--device", type=choice, default=None, cls=ShownDefault, config_field=config_field,
                            help=help)
    return click.option("--device", type=choice, default="auto", show_default=True, help=help)


def config_choice(source: str, *extra: str) -> ConfigChoice:
    """Choices from `"module:Name"` (a Literal alias, an Enum, a dict's keys or a tuple) or from
    `"module:Class.field"` (the Literal annotation of a dataclass field); `extra` values follow them
    (e.g. "all")."""
    return ConfigChoice(source, extra)


def _resolve(source: str) -> Any:
    module_name, _, attr = source.partition(":")
    name, _, field = attr.partition(".")
    obj = getattr(importlib.import_module(module_name), name)
    return typing.get_type_hints(obj)[field] if field else obj


def _values(obj: Any) -> tuple[str, ...]:
    if typing.get_origin(obj) is typing.Literal:
        return tuple(str(v) for v in typing.get_args(obj))
    if isinstance(obj, type) and issubclass(obj, enum.Enum):
        return tuple(str(m.value) for m in obj)
    return tuple(obj)  # a tuple, or a dict's keys


def root_options(help: str = ROOT_HELP) -> Callable[[F], F]:
    """`--root DIR` (required) and `--version` (the version folder under it)."""
    root = click.option("--root", required=True, metavar="DIR", help=help)
    version = click.option("--version", default=None,
                           help="Version folder (v1.0-trainval, v1.0-mini, ...); auto if only one.")
    return lambda fn: root(version(fn))


def store_option(default: str | None = DEFAULT_STORE, help: str = STORE_HELP) -> Callable[[F], F]:
    """`--store STORE`. A plain string, not click.Path: click would turn an fsspec URL such as
    file:///x/y.zarr into file:/x/y.zarr."""
    return click.option("--store", default=default, show_default=default is not None, metavar="STORE", help=help)


def split_option(help: str = "Dataset split to run on.", auto: bool = True) -> Callable[[F], F]:
    """`--split SPLIT`: one dataset split (`--split` means a dataset split in every command), None when not
    given. `auto`: the command then runs on `store_split`'s choice (its help says so); else `help` says
    what None means."""
    return click.option("--split", default=None, cls=ShownDefault, default_text=AUTO_SPLIT if auto else None,
                        metavar="SPLIT", help=f"{help.rstrip('.')} ({SPLITS}).")


def store_split(store: str, split: str | None) -> str:
    """`split` when given, else the store's `val` or its only split, with a `note:` line on stderr when it
    is not `val` (stdout stays the command's result, e.g. its JSON)."""
    if split is not None:
        return split
    from occdata.store.splits import store_default_split

    chosen = store_default_split(store)
    if chosen.note is not None and os.environ.get("RANK", "0") == "0":  # once under torchrun
        click.echo(f"note: {chosen.note}", err=True)
    return chosen.split


def splits_option(help: str = "Only scenes of this split (repeatable)") -> Callable[[F], F]:
    """`--split SPLIT`, repeatable, handed to the command as the tuple `splits` (empty: every split)."""
    return click.option("--split", "splits", multiple=True, metavar="SPLIT", help=f"{help}: {SPLITS}")


def renamed_option(old: str, new: str, param: str, **kwargs: Any) -> Callable[[F], F]:
    """The old spelling `old` of the option `new` (whose value the command gets as `param`), hidden from
    --help and still accepted for a while: it prints a one-line note on stderr and stands for `new`.
    `kwargs` are the old option's click arguments (its type, or `is_flag=True`)."""
    dest = f"renamed_{param}"

    def decorate(fn: F) -> F:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kw: Any) -> Any:
            value = kw.pop(dest)
            ctx = click.get_current_context()
            if ctx.get_parameter_source(dest) is ParameterSource.COMMANDLINE:
                if ctx.get_parameter_source(param) is ParameterSource.COMMANDLINE:
                    raise click.UsageError(f"give {new} alone ({old} is its old spelling)")
                click.echo(f"note: {old} is now {new} (the old spelling still works, for a while)", err=True)
                kw[param] = value
            return fn(*args, **kw)

        return click.option(old, dest, hidden=True, **kwargs)(wrapper)  # type: ignore[return-value]

    return decorate


def removed_option(old: str, instead: str) -> Callable[[F], F]:
    """A flag that is gone, hidden from --help: giving it is one error line that names what to type instead
    (it meant something else than a name still in use, so it is not quietly mapped)."""

    def refuse(ctx: click.Context, param: click.Parameter, value: bool) -> None:
        if value:
            raise click.ClickException(f"{old} is gone: use {instead}")

    return click.option(old, is_flag=True, hidden=True, expose_value=False, callback=refuse)


def progress_option(help: str = "No progress bar.") -> Callable[[F], F]:
    """`--no-progress`, handed to the command as `progress` (True unless given)."""
    return click.option("--no-progress", "progress", flag_value=False, default=True, show_default=False, help=help)


def grid_range_option(which: str = "The custom grid's") -> Callable[[F], F]:
    """`--range XMIN YMIN ZMIN XMAX YMAX ZMAX`, handed to the command as `grid_range` (None: Occ3D's)."""
    occ3d = " ".join(f"{v:g}" for v in (*GRID.lower, *GRID.upper))
    return click.option("--range", "grid_range", type=float, nargs=6, default=None,
                        metavar="XMIN YMIN ZMIN XMAX YMAX ZMAX",
                        help=f"{which} range in metres (key ego; default Occ3D's {occ3d}).")


def json_option(help: str = "Print the result as JSON.") -> Callable[[F], F]:
    """`--json`, handed to the command as `as_json`."""
    return click.option("--json", "as_json", is_flag=True, help=help)


def cluster_options(per_worker: str = "") -> Callable[[F], F]:
    """`--workers` and `--scheduler`, handed to the command as one `cluster`
    (occdata.runtime.cluster.ClusterConfig, which validates them). `per_worker`: what each worker
    does, for the help text (", one scene each at a time")."""

    def decorate(fn: F) -> F:
        @functools.wraps(fn)
        def wrapper(*args: Any, workers: int, scheduler: str | None, **kwargs: Any) -> Any:
            from occdata.runtime.cluster import ClusterConfig

            try:
                cluster = ClusterConfig(workers=workers, scheduler=scheduler)
            except OccDataError as exc:
                raise click.ClickException(str(exc)) from None
            return fn(*args, cluster=cluster, **kwargs)

        workers = click.option("--workers", type=int, default=1, show_default=True,
                               help=f"Worker processes of the embedded Dask LocalCluster{per_worker} "
                                    "(1: in this process).")
        scheduler = click.option("--scheduler", default=None, metavar="ADDRESS",
                                 help="Run on an existing Dask cluster (tcp://host:8786; default "
                                      "$DASK_SCHEDULER_ADDRESS) instead of a LocalCluster; its workers must "
                                      "see --root and --out at the same paths.")
        return workers(scheduler(wrapper))  # type: ignore[return-value]

    return decorate


def rig_options() -> Callable[[F], F]:
    """`--cameras`, `--lidars` and `--reference-lidar`, handed to the command as one `rig`
    (occdata.nuscenes.rig.RigChoice, which validates them). Default: every camera and LiDAR of the
    tables (`occdata scan` lists them)."""

    def decorate(fn: F) -> F:
        @functools.wraps(fn)
        def wrapper(*args: Any, cameras: str | None, lidars: str | None, reference_lidar: str | None,
                    **kwargs: Any) -> Any:
            from occdata.nuscenes.rig import RigChoice

            try:
                rig = RigChoice.parse(cameras, lidars, reference_lidar)
            except OccDataError as exc:
                raise click.ClickException(str(exc)) from None
            return fn(*args, rig=rig, **kwargs)

        cams = click.option("--cameras", default=None, metavar="CH,CH,...",
                            help="Cameras to use, in this order (the network's camera order). Default: every "
                                 "camera of sensor.json with keyframes; nuScenes' six in their model order "
                                 "first, others by name.")
        lids = click.option("--lidars", default=None, metavar="CH,CH,...",
                            help="LiDARs to use (depth targets, labels, masks merge them all). Default: every "
                                 "LiDAR of sensor.json with keyframes.")
        ref = click.option("--reference-lidar", default=None, metavar="CH",
                           help="The LiDAR whose keyframe timestamp and ego pose define the key-ego frame. "
                                "Default: LIDAR_TOP where there is one, else the first LiDAR by name.")
        return cams(lids(ref(wrapper)))  # type: ignore[return-value]

    return decorate


def split_source_options() -> Callable[[F], F]:
    """`--split-file` and `--unlisted-split`, handed to the command as one `scene_splits`
    (occdata.nuscenes.splits.SplitChoice): where each scene's split comes from."""

    def decorate(fn: F) -> F:
        @functools.wraps(fn)
        def wrapper(*args: Any, split_file: str | None, unlisted_split: str, **kwargs: Any) -> Any:
            from occdata.nuscenes.splits import SplitChoice

            try:
                choice = SplitChoice(file=Path(split_file) if split_file else None, unlisted=unlisted_split)
            except OccDataError as exc:
                raise click.ClickException(str(exc)) from None
            return fn(*args, scene_splits=choice, **kwargs)

        file = click.option("--split-file", default=None, metavar="FILE",
                            help='Each scene\'s split, as JSON: {"train": ["scene name", ...], "val": [...]}. It '
                                 "decides for every scene it names, before nuScenes' official lists.")
        unlisted = click.option("--unlisted-split", default="auto", show_default=True, metavar="NAME",
                                help="The split of scenes that no list (split file, nuScenes' official lists, a "
                                     "split=NAME tag in the scene description) names: auto = train, with one "
                                     "scene in five (by a hash of its name) in val; or a name, e.g. unassigned.")
        return file(unlisted(wrapper))  # type: ignore[return-value]

    return decorate
