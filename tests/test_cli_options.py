"""Issue 34 item 5: the options the commands share (cli/options.py), their choices read from the configs
that define them, and the one Ctrl-C / SIGTERM helper (cli/_common.exit_on_interrupt)."""

from __future__ import annotations

import signal
import typing

import click
import pytest
from click.testing import CliRunner

from cli._common import exit_on_interrupt
from cli.fastocc_cli import main as fastocc_main
from cli.occdata_cli import main as occdata_main
from cli.options import ConfigChoice
from occdata.runtime.cluster import Interrupted

COMMANDS = [(g, name) for g in (occdata_main, fastocc_main) for name in g.commands]


@pytest.mark.parametrize(("group", "name"), COMMANDS, ids=[f"{g.name}-{n}" for g, n in COMMANDS])
def test_every_help_renders_and_every_config_choice_resolves(group: click.Group, name: str) -> None:
    r = CliRunner().invoke(group, [name, "--help"])
    assert r.exit_code == 0, r.output
    for p in group.commands[name].params:
        if isinstance(p.type, ConfigChoice):
            assert p.type.choices, p.name
            if isinstance(p.default, str):
                assert p.default in p.type.choices, (p.name, p.default, p.type.choices)


def _choices(group: click.Group, command: str, option: str) -> tuple[str, ...]:
    param = next(p for p in group.commands[command].params if p.name == option)
    assert isinstance(param.type, ConfigChoice), option
    return param.type.choices


def test_choices_are_the_configs() -> None:
    from fastocc.bench import RUNTIMES
    from fastocc.model.config import PRESETS, HeadKind
    from fastocc.train.config import WARN_SIGNALS
    from occdata.eval.evaluate import MaskName
    from occdata.view.config import MASK_CHOICES, STYLES, VIEWS

    assert _choices(occdata_main, "eval", "mask") == typing.get_args(MaskName)
    assert _choices(occdata_main, "build", "on_error") == ("fail", "skip")
    assert _choices(occdata_main, "view", "view_name") == tuple(VIEWS)
    assert _choices(occdata_main, "view", "mask") == MASK_CHOICES
    assert _choices(occdata_main, "view", "style") == tuple(STYLES)
    assert _choices(fastocc_main, "train", "preset_name") == tuple(PRESETS)
    assert _choices(fastocc_main, "train", "head") == tuple(k.value for k in HeadKind)
    assert _choices(fastocc_main, "bench", "head") == (*(k.value for k in HeadKind), "all")
    assert _choices(fastocc_main, "bench", "runtimes") == (*RUNTIMES, "all")
    assert _choices(fastocc_main, "train", "warn_signal") == WARN_SIGNALS


@click.command()
@click.option("--signum", type=int, default=None)
def _interruptible(signum: int | None) -> None:
    with exit_on_interrupt("interrupted: rerun with --resume"):
        raise KeyboardInterrupt if signum is None else Interrupted(signum)


@pytest.mark.parametrize(("args", "status"), [([], 130), (["--signum", str(int(signal.SIGTERM))], 143)])
def test_interrupt_is_one_message_and_128_plus_the_signal(args: list[str], status: int) -> None:
    r = CliRunner().invoke(_interruptible, args)
    assert r.exit_code == status
    assert r.stderr == "\ninterrupted: rerun with --resume\n"


@pytest.mark.parametrize("command", ["build", "labels"])
def test_cluster_options_are_validated_by_cluster_config_in_one_line(command: str, tmp_path) -> None:
    r = CliRunner().invoke(occdata_main, [command, "--root", str(tmp_path), "--out", str(tmp_path / "o"),
                                          "--workers", "0"])
    assert r.exit_code == 1
    assert r.stderr.strip().splitlines()[-1] == "Error: --workers must be >= 1, got 0"
    assert not (tmp_path / "o").exists()


# -- one name, one meaning (issue 41 item 5) ---------------------------------------------------------------
def _visible_options(group: click.Group) -> list[tuple[str, str, click.Option]]:
    return [(name, opt, p) for name, cmd in group.commands.items() for p in cmd.params
            if isinstance(p, click.Option) and not p.hidden for opt in p.opts]


def test_an_option_is_a_flag_everywhere_or_nowhere() -> None:
    """`--lidar-sweeps` was a flag in `labels` and a number in `build`; `--split` a flag in `bench`."""
    kinds: dict[str, set[tuple[str, bool]]] = {}
    for group in (occdata_main, fastocc_main):
        for name, opt, p in _visible_options(group):
            kinds.setdefault(opt, set()).add((f"{group.name} {name}", p.is_flag))
    mixed = {opt: sorted(k) for opt, k in kinds.items() if len({flag for _, flag in k}) > 1}
    assert not mixed, mixed


def test_split_is_a_dataset_split_wherever_it_is_declared() -> None:
    found = [(group.name, name, p) for group in (occdata_main, fastocc_main)
             for name, opt, p in _visible_options(group) if opt == "--split"]
    assert len(found) >= 7
    for group_name, name, p in found:
        assert not p.is_flag and p.metavar == "SPLIT", (group_name, name)
        assert "train, val, test" in (p.help or ""), (group_name, name, p.help)
    assert not [n for n, opt, _ in _visible_options(fastocc_main) if opt == "--batch"]


class _Called(SystemExit):
    """Raised by a stand-in for the function a command calls, carrying what the command handed it. A
    SystemExit: the commands turn every Exception into one `Error:` line (cli._common.friendly_errors),
    and click's runner passes a SystemExit through as the run's exit."""

    def __init__(self, args: tuple[object, ...], kwargs: dict[str, object]) -> None:
        super().__init__(0)
        self.call = (args, kwargs)


def _stand_in(monkeypatch: pytest.MonkeyPatch, target: str) -> list[tuple[tuple[object, ...], dict[str, object]]]:
    calls: list[tuple[tuple[object, ...], dict[str, object]]] = []

    def called(*args: object, **kwargs: object) -> None:
        calls.append((args, kwargs))
        raise _Called(args, kwargs)

    monkeypatch.setattr(target, called)
    return calls


def _call(monkeypatch: pytest.MonkeyPatch, group: click.Group, args: list[str], target: str) -> tuple[object, str]:
    """What the command hands `target` for `args`, and its stderr."""
    calls = _stand_in(monkeypatch, target)
    r = CliRunner().invoke(group, args)
    assert len(calls) == 1, (r.output, r.exception)
    call_args, call_kwargs = calls[0]
    return (call_args[0] if call_args else next(iter(call_kwargs.values()))), r.stderr


@pytest.mark.parametrize(("new", "old"), [(["--all-sweeps"], ["--lidar-sweeps"])])
def test_labels_all_sweeps_and_its_old_spelling(monkeypatch: pytest.MonkeyPatch, tmp_path, new: list[str],
                                                old: list[str]) -> None:
    base = ["labels", "--root", str(tmp_path), "--out", str(tmp_path / "o")]
    cfg, err = _call(monkeypatch, occdata_main, base + new, "occdata.labels.generate_labels")
    assert cfg.options.all_sweeps is True and err == ""
    cfg, err = _call(monkeypatch, occdata_main, base + old, "occdata.labels.generate_labels")
    assert cfg.options.all_sweeps is True
    assert err == "note: --lidar-sweeps is now --all-sweeps (the old spelling still works, for a while)\n"
    cfg, err = _call(monkeypatch, occdata_main, base, "occdata.labels.generate_labels")
    assert cfg.options.all_sweeps is False and err == ""


def _called_kwargs(monkeypatch: pytest.MonkeyPatch, group: click.Group, args: list[str],
                   target: str) -> tuple[typing.Any, dict[str, typing.Any]]:
    calls = _stand_in(monkeypatch, target)
    r = CliRunner().invoke(group, args)
    assert len(calls) == 1, (r.output, r.exception)
    return r, calls[0][1]


def test_build_gts_grid_and_its_old_spelling(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    base = ["build", "--root", str(tmp_path), "--out", str(tmp_path / "o.zarr")]
    target = "occdata.store.build.BuildConfig"
    r, kwargs = _called_kwargs(monkeypatch, occdata_main, base + ["--gts-grid", "surroundocc"], target)
    assert kwargs["grid"].name == "surroundocc" and r.stderr == ""
    r, kwargs = _called_kwargs(monkeypatch, occdata_main, base + ["--grid", "surroundocc"], target)
    assert kwargs["grid"].name == "surroundocc"
    assert r.stderr == "note: --grid is now --gts-grid (the old spelling still works, for a while)\n"
    r, kwargs = _called_kwargs(monkeypatch, occdata_main, base, target)
    assert kwargs["grid"] is None and r.stderr == ""
    r = CliRunner().invoke(occdata_main, base + ["--grid", "occ3d", "--gts-grid", "occ3d"])
    assert r.exit_code == 2 and "give --gts-grid alone (--grid is its old spelling)" in r.stderr


def test_bench_batch_size_and_stage_split_and_their_old_spellings(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg, err = _call(monkeypatch, fastocc_main, ["bench", "--batch-size", "3"], "fastocc.bench.run_benchmark")
    assert cfg.batch == 3 and err == ""
    cfg, err = _call(monkeypatch, fastocc_main, ["bench", "--batch", "3"], "fastocc.bench.run_benchmark")
    assert cfg.batch == 3
    assert err == "note: --batch is now --batch-size (the old spelling still works, for a while)\n"
    cfg, err = _call(monkeypatch, fastocc_main, ["bench", "--stage-split", "--preset", "nano"],
                     "fastocc.bench.run_split_benchmark")
    assert cfg.presets == ("nano",) and err == ""
    cfg, err = _call(monkeypatch, fastocc_main, ["bench", "--split", "--preset", "nano"],
                     "fastocc.bench.run_split_benchmark")
    assert cfg.presets == ("nano",)
    assert err == "note: --split is now --stage-split (the old spelling still works, for a while)\n"


def test_store_help_is_written_once() -> None:
    import cli.fastocc_cli
    import cli.options

    assert cli.fastocc_cli.STORE_HELP is cli.options.STORE_HELP
    helps = [p.help for _, opt, p in _visible_options(fastocc_main) if opt == "--store"]
    assert len(helps) >= 4 and all(h.startswith(cli.options.STORE_HELP) for h in helps), helps
