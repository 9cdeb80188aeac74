"""Argument errors (issue 34): one line on stderr naming the command and the argument, exit code 2, never a
traceback or a usage block; a misspelt command, choice or option gets the close one suggested; numbers are
checked against their natural range; a bad value is blamed on where it came from (the command line or the
file). The walk finds every command and subcommand in the real parser, so a new one is covered without a
list to keep; the parser runs in this process (no command is ever run: each argv is bad on purpose), a few
checks run the real command in a subprocess as a shell user would."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from mntes_stream.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "mntes_stream"]


def _commands(parser, path=()):
    """``(path, parser)`` of every command that runs (a leaf) and of every one that takes a subcommand."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if path:
        yield path, parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from _commands(sub, (*path, name))


def _leaves(parser):
    return [(path, p) for path, p in _commands(parser)
            if not any(isinstance(a, argparse._SubParsersAction) for a in p._actions)]


PARSER = build_parser()
LEAVES = _leaves(PARSER)


def _values(action, value: str) -> list[str]:
    n = action.nargs
    if n in (None, "?", "+", argparse.ONE_OR_MORE) or n == 1:
        return [value]
    if isinstance(n, int):
        return [value] * n
    return []  # "*": none needed


def _argv(parser, target=None, values=()) -> list[str]:
    """Valid-looking values for the required arguments of ``parser``, in its order, and ``values`` for
    ``target`` in its place (positionals are matched by position)."""
    out: list[str] = []
    for a in parser._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if a is target:
            out += [*a.option_strings[:1], *values]
            continue
        if a.option_strings and not a.required:
            continue
        value = str(next(iter(a.choices))) if a.choices else "1"
        out += [*a.option_strings[:1], *_values(a, value)]
    return out


def _one_line(capsys, argv: list[str]) -> str:
    """Parse ``argv`` with the real parser: it must refuse with exit code 2 and exactly one line on stderr."""
    with pytest.raises(SystemExit) as exc:
        PARSER.parse_args(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert exc.value.code == 2, (argv, err)
    assert len(lines) == 1 and "Traceback" not in err and "usage:" not in err, (argv, err)
    return lines[0]


def test_the_walk_finds_every_command():
    names = {" ".join(p) for p, _ in LEAVES}
    # Spot checks that the walk reaches nested commands too (not a list to keep: the walk is the list).
    assert {"up", "serve", "calib fit", "tables build", "bench convert"} <= names, sorted(names)
    assert len(names) > 30


def test_an_unknown_option_is_one_line_naming_it(capsys):
    for path, parser in LEAVES:
        argv = [*path, *_argv(parser), "--no-such-option"]
        line = _one_line(capsys, argv)
        assert line.startswith(f"mntes-stream {' '.join(path)}: error: unrecognized arguments: --no-such-option"), \
            (argv, line)


BAD = "bogus value!"  # no number, no choice, no name (names match core.ids.NAME_PATTERN)


def _refuses(kind, text: str) -> bool:
    if kind is None or kind is str:
        return False
    try:
        kind(text)
    except (ValueError, TypeError, argparse.ArgumentTypeError):
        return True
    return False


def test_a_bad_value_of_every_typed_option_is_one_line_naming_it(capsys):
    checked = 0
    for path, parser in LEAVES:
        for a in parser._actions:
            if a.help is argparse.SUPPRESS or isinstance(a, argparse._HelpAction) or a.nargs == 0:
                continue
            if a.choices is None and not _refuses(a.type, BAD):
                continue  # a free string (a path, an id): no value is bad for the parser
            bad = _values(a, BAD) or [BAD]
            argv = [*path, *_argv(parser, a, bad)]
            line = _one_line(capsys, argv)
            named = a.option_strings or [a.metavar or a.dest]
            assert line.startswith(f"mntes-stream {' '.join(path)}: error: argument "), (argv, line)
            assert any(str(n) in line for n in named) and BAD in line, (argv, line)
            checked += 1
    assert checked > 100


def test_a_missing_required_argument_is_one_line_naming_it(capsys):
    checked = 0
    for path, parser in _commands(PARSER):
        required = [a for a in parser._actions if (a.required or not a.option_strings) and
                    not isinstance(a, argparse._HelpAction) and a.nargs not in ("*", "?")]
        if not required:
            continue
        line = _one_line(capsys, list(path))
        assert "the following arguments are required:" in line, (path, line)
        for a in required:
            assert (a.option_strings[0] if a.option_strings else (a.metavar or a.dest)) in line, (path, line)
        checked += 1
    assert checked >= 10


def test_numbers_are_finite_everywhere_outside_the_benchmarks(capsys):
    """Every numeric flag of a command refuses NaN (a float flag of plain argparse takes it); benchmarks
    (mntes_stream/bench/) keep their own flags."""
    checked = 0
    for path, parser in LEAVES:
        if path[0] == "bench":
            continue
        for a in parser._actions:
            if getattr(a.type, "__name__", None) not in ("int", "float") or a.help is argparse.SUPPRESS:
                continue
            argv = [*path, *_argv(parser, a, _values(a, "nan") or ["nan"])]
            line = _one_line(capsys, argv)
            assert "expected " in line and "got 'nan'" in line, (argv, line)
            checked += 1
    assert checked > 50


@pytest.mark.parametrize("argv, says", [
    (["up", "--duration", "-1"], "mntes-stream up: error: argument --duration: expected a number (s) >= 0, got '-1'"),
    (["up", "--modules", "0"], "argument --modules: expected an integer >= 1, got '0'"),
    (["up", "--metrics-port", "70000"], "argument --metrics-port: expected an integer >= 0 and <= 65535"),
    (["simulate", "--chunk-s", "0"], "argument --chunk-s: expected a number (s) > 0, got '0'"),
    (["record", "--rotate-mb", "-5"], "argument --rotate-mb: expected a number (MiB) >= 0, got '-5'"),
    (["ps", "--timeout", "0"], "argument --timeout: expected a number (s) > 0"),
    (["simulate", "--nuller-gain", "16"], "expected an integer >= 0 and <= 15, got '16'"),
    (["convert", "run.g3", "out.mcap", "--t-bath-default-k", "0"], "argument --t-bath-default-k: expected a number (K) > 0"),
])
def test_out_of_range_is_refused(capsys, argv, says):
    assert says in _one_line(capsys, argv)


@pytest.mark.parametrize("argv, says", [
    (["upp"], "mntes-stream: error: unknown command 'upp'; did you mean 'up'?"),
    (["Up"], "did you mean 'up'?"),
    (["calib", "fitt"], "mntes-stream calib: error: unknown action 'fitt'; did you mean 'fit'?"),
    (["up", "--durration", "5"], "unrecognized arguments: --durration 5; did you mean --duration?"),
    (["up", "--kind", "tabel"], "invalid choice: 'tabel'; did you mean 'table'?"),
    # A setting's choices too (add_settings_args): the recorder's compression.
    (["record", "--compression", "lz5"], "invalid choice: 'lz5'; did you mean 'lz4'?"),
    # How a G3 file is read (G3InputConfig's declarations), for convert and params alike.
    (["convert", "run.g3", "out.mcap", "--t-bath-unit", "mk"], "invalid choice: 'mk'; did you mean 'mK'?"),
    (["params", "--from", "run.g3", "--params", "p.toml", "--out", "o.toml", "--t-bath-unit", "k"],
     "invalid choice: 'k'; did you mean 'K'?"),
])
def test_a_misspelling_gets_the_close_name(capsys, argv, says):
    assert says in _one_line(capsys, argv)


def _run(*args, **kw):
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=120, **kw)


def test_as_a_shell_user_sees_it():
    """The real command: one line, exit code 2, for a misspelt command and a negative duration."""
    for argv, says in ((["upp"], "did you mean 'up'?"), (["up", "--duration", "-1"], "expected a number (s) >= 0")):
        res = _run(*argv)
        assert res.returncode == 2 and res.stderr.count("\n") == 1 and says in res.stderr, res.stderr
        assert res.stdout == ""


def test_a_bad_value_is_blamed_on_where_it_came_from(tmp_path):
    """`--set` on the command line is named as such; the same bad value in the file names the file."""
    res = _run("serve", "--config", ROOT / "services" / "recorder.toml", "--set", "recorder.flush_interval_s=-1")
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip() == ("mntes-stream: error: command line --set [recorder] flush_interval_s: expected a "
                                  "number (s) > 0, got -1")
    bad = tmp_path / "recorder.toml"
    bad.write_text("[recorder]\nflush_interval_s = -1\n")
    res = _run("serve", "--config", bad)
    assert res.returncode == 2
    assert res.stderr.strip() == f"mntes-stream: error: {bad} [recorder] flush_interval_s: expected a number (s) > 0, got -1"
    # A good file with a bad --set: the command line is blamed, not the file (issue 34: it named services/converter.toml).
    res = _run("config", "show", ROOT / "services" / "converter.toml", "--set", "converter.kind=exactt")
    assert res.returncode == 2
    assert res.stderr.startswith("mntes-stream: error: command line --set [converter] kind: expected one of")
    res = _run("config", "show", ROOT / "services" / "converter.toml", "--set", "converter.no_such_key=1")
    assert res.returncode == 2 and "command line --set 'converter.no_such_key=1': [converter] has no setting" in res.stderr


def test_docs_cli_examples_are_what_the_command_says(capsys):
    """docs/cli.md "Argument errors": each `$ mntes-stream ...` line and the error line under it, as written."""
    import shlex

    text = (ROOT / "docs" / "cli.md").read_text().split("\n## Argument errors\n", 1)[1].split("\n## ", 1)[0]
    lines = text.split("```\n", 2)[1].splitlines()
    pairs = [(lines[i], lines[i + 1]) for i in range(0, len(lines) - 1, 2)]
    assert len(pairs) >= 4 and all(cmd.startswith("$ mntes-stream ") for cmd, _ in pairs), lines
    for cmd, says in pairs:
        assert _one_line(capsys, shlex.split(cmd)[2:]) == says, cmd
