"""A command line imports only the subcommand it names (issue #38): the listing, each subcommand's help and
the usage errors are the same as with every subcommand registered by its module."""

from __future__ import annotations

import argparse

import pytest

from cellcal.core.cli.app import SUBCOMMANDS, SUMMARIES, build_parser, run_command


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:  # type: ignore[type-arg]
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def test_each_summary_is_the_line_its_module_registers() -> None:
    listed = {a.dest: a.help for a in _subparsers(build_parser())._choices_actions}
    assert listed == SUMMARIES
    assert tuple(listed) == SUBCOMMANDS  # and in the same order


def test_the_listing_without_the_modules_is_the_listing_with_them() -> None:
    assert build_parser(()).format_help() == build_parser().format_help()


def test_the_listing_registers_no_subcommand_in_full() -> None:
    choices = _subparsers(build_parser(())).choices
    assert sorted(choices) == sorted(SUBCOMMANDS)
    assert all(not p._actions[1:] for p in choices.values())  # only -h: no module's options


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_a_subcommands_help_is_the_full_parsers(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        run_command([name, "--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out == _subparsers(build_parser()).choices[name].format_help()


@pytest.mark.parametrize("argv", [["bogus"], [], ["--bogus"], ["-5", "calibrate"], ["calibrate", "--bogus"],
                                  ["devices", "--scan", "--subnet", "10.0.0.0/8"], ["paper", "--true-angle"]])
def test_usage_errors_are_the_full_parsers(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as full:
        build_parser().parse_args(argv)
    expected = capsys.readouterr()
    with pytest.raises(SystemExit) as lazy:
        run_command(argv)
    got = capsys.readouterr()
    assert (lazy.value.code, got.err, got.out) == (full.value.code, expected.err, expected.out)
    assert lazy.value.code == 2 and "error:" in got.err
