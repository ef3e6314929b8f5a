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
