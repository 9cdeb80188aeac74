"""Helpers shared by CLI subcommands."""

from __future__ import annotations

import argparse
import dataclasses
from typing import TYPE_CHECKING

from mntes_stream.errors import ConfigError

# Shared with bench/, which sits below cli/: defined once in mntes_stream.options, named here for the commands.
from mntes_stream.options import add_zenoh_args as add_zenoh_args
from mntes_stream.options import deprecated_alias as deprecated_alias
from mntes_stream.options import zenoh_layer as zenoh_layer

if TYPE_CHECKING:  # core.params imports numpy (0.1 s): a command that takes no --params need not pay for it
    from mntes_stream.core.params import DetectorParams


class OneLineParser(argparse.ArgumentParser):
    """A parser whose errors are one line on stderr naming the command, with the close spelling suggested.

    argparse prints its usage block before an error (18 lines for ``up``); a
    shell user needs the command, the argument and what is wrong, as every
    other error of the command is said (``mntes-stream: error: ...``), and a
    ``did you mean`` where a command, choice or option is misspelt. Exit code 2.
    """

    def error(self, message):
        text = " ".join(str(message).split())
        if "arguments are required" in text:
            text += f" (`{self.prog} --help` describes them)"
        self.exit(2, f"{self.prog}: error: {text}\n")

    def _check_value(self, action, value):
        # argparse's own check, worded for a shell: the command or choice closest to what was typed.
        if action.choices is None or value in action.choices:
            return
        near = _closest(str(value), [str(c) for c in action.choices])
        hint = f"; did you mean {near!r}?" if near else ""
        if isinstance(action, argparse._SubParsersAction):
            what = {"COMMAND": "command", "NAME": "benchmark"}.get(action.metavar, (action.metavar or "command").lower())
            raise argparse.ArgumentError(None, f"unknown {what} {value!r}{hint} (`{self.prog} --help` lists them)")
        listed = ", ".join(repr(c) for c in action.choices)
        raise argparse.ArgumentError(action, f"invalid choice: {value!r}{hint} (choose from {listed})")

    def parse_args(self, args=None, namespace=None):
        namespace, extra = self.parse_known_args(args, namespace)
        if extra:
            parser = _innermost(self, namespace)
            parser.error(_unrecognized(parser, extra))
        return namespace


def _closest(word: str, names: list[str]) -> str | None:
    """The name closest to ``word``: the same in another case, the one it begins, else difflib's nearest."""
    import difflib

    same = [n for n in names if n.lower() == word.lower()]
    starts = [n for n in names if len(word) >= 2 and n.startswith(word)]
    near = same or (starts if len(starts) == 1 else []) or difflib.get_close_matches(word, names, n=1, cutoff=0.6)
    return near[0] if near else None


def _innermost(parser, namespace):
    """The (sub)command parser ``namespace`` was parsed by: the one whose arguments an unknown one was meant for."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = getattr(namespace, action.dest, None)
            if chosen in action.choices:
                return _innermost(action.choices[chosen], namespace)
    return parser


def _unrecognized(parser, extra: list[str]) -> str:
    """One line for arguments no parser took, with the visible option closest to the first unknown one."""
    text = f"unrecognized arguments: {' '.join(extra)}"
    first = next((e for e in extra if e.startswith("-")), None)
    if first is None:
        return text
    # Compared without the dashes every long option shares, which would make any two look alike.
    options = {s.lstrip("-"): s for a in parser._actions if a.help is not argparse.SUPPRESS for s in a.option_strings}
    near = _closest(first.split("=", 1)[0].lstrip("-"), list(options))
    return f"{text}; did you mean {options[near]}?" if near else text


class CommandParser(OneLineParser):
    """A command's parser whose arguments are added when it first parses or prints its help.

    ``mntes-stream COMMAND`` then builds the arguments of COMMAND alone: the
    others' need their modules' settings classes (the recorder's, the
    monitor's, every service's summary), whose imports cost more CPU than a
    short command itself (``convert --help`` took 0.75 s). ``mntes-stream
    --help`` needs only each command's name and one-line help, given to
    ``add_parser`` at once.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._fill = None
        self._describe = None

    def fill_later(self, fill) -> None:
        self._fill = fill

    def describe_later(self, describe) -> None:
        """``describe()`` gives the description when the help is printed, not before (``serve``'s lists
        every service, which imports every service's module: 0.9 CPU s that a service starting needs not)."""
        self._describe = describe

    def filled(self) -> CommandParser:
        """This parser with its arguments added (once)."""
        fill, self._fill = self._fill, None
        if fill is not None:
            fill(self)
        return self

    def parse_known_args(self, args=None, namespace=None):
        return super(CommandParser, self.filled()).parse_known_args(args, namespace)

    def format_usage(self) -> str:
        return super(CommandParser, self.filled()).format_usage()

    def format_help(self) -> str:
        parser = self.filled()
        if parser._describe is not None:
            parser.description, parser._describe = parser._describe(), None
        return super(CommandParser, parser).format_help()


def description(p, describe) -> None:
    """``describe()`` is ``p``'s description: when its help is printed (a :class:`CommandParser`), else now."""
    if isinstance(p, CommandParser):
        p.describe_later(describe)
    else:
        p.description = describe()


def arguments(p, fill) -> None:
    """``fill(p)`` adds the command's arguments: when ``p`` is used (a :class:`CommandParser`), else now."""
    if isinstance(p, CommandParser):
        p.fill_later(fill)
    else:
        fill(p)


def setup_logging(verbose: bool) -> None:
    """INFO (``verbose``) or WARNING to stderr, one format for every command."""
    import logging

    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(asctime)s %(processName)s %(name)s: %(message)s")


def add_params_args(parser) -> None:
    parser.add_argument("--params", metavar="FILE", help="detector parameter file (TOML); default: the paper's Table 1 detector")
    parser.add_argument("--detector", metavar="ID", help="detector id in --params (default: the first)")


def params_from_args(args) -> DetectorParams:
    from mntes_stream.core.params import table1_params

    if not args.params:
        if args.detector:
            raise ConfigError("--detector needs --params")
        return table1_params()
    from mntes_stream.io.paramfile import load_params

    detectors = load_params(args.params)
    if args.detector is None:
        return next(iter(detectors.values()))
    try:
        return detectors[args.detector]
    except KeyError:
        raise ConfigError(f"detector {args.detector!r} not in {args.params}") from None


def zenoh_from_args(args, table=None):
    """Effective zenoh settings: the flags over ``table`` (a config's ``[zenoh]``, default: none)."""
    from mntes_stream.io.transport import ZenohSettings

    return zenoh_layer(args).over(table if table is not None else ZenohSettings())


_CANONICAL = ("--duration", "--out")


def add_settings_args(p, cls, names, aliases: dict | None = None, title: str | None = None, *,
                      spelled: dict | None = None, repeatable=(), metavars: dict | None = None) -> None:
    """``--name`` flags for settings of ``cls``, typed and documented from their declarations.

    Every flag defaults to None (not given), so a flag overrides a config file
    only where it is given; :func:`settings_from_args` collects them.

    ``aliases``: more spellings of a flag (``--duration``, ``--out``: the grammar's, the generated one hidden).
    ``spelled``: a flag's one spelling where it is not the setting's name (flags older than their setting:
    ``--hk-every`` for ``hk_every_s``; ``--no-board-hk`` for a bool that defaults True: it sets it False).
    ``repeatable``: tuple settings given once per value (``--board 1 --board 2``), not as one list.
    ``metavars``: a flag's placeholder where the setting's name or unit says less (``IP=SERIAL``).
    """
    import typing

    from mntes_stream.core.settings import declared, expected

    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    g = p.add_argument_group(title) if title else p
    for name in names:
        s, hint = declared(fields[name]), hints[name]
        generated, extra = f"--{name.replace('_', '-')}", tuple((aliases or {}).get(name, ()))
        # The grammar's spelling wins (--duration, not --duration-s); the generated one stays a hidden alias.
        canonical = [a for a in extra if a in _CANONICAL]
        flags = [*canonical, *(a for a in extra if a not in _CANONICAL)] if canonical else [generated, *extra]
        if spelled and name in spelled:
            flags, canonical = [spelled[name], *extra], []
        default = fields[name].default
        many = typing.get_origin(hint) is tuple
        inner = typing.get_args(hint)[0] if many else _not_none(hint)
        choices = s.choices if not many and inner is str and s.choices else None
        if choices:  # argparse checks them: its one line names the closest choice (OneLineParser)
            parse = str
        elif not many and inner in (int, float, str):
            parse = _declared_type(cls, name, hint, s, inner)
        elif many and name in repeatable and inner in (int, float):
            from mntes_stream.options import number

            parse = number(inner, s.unit or "", ge=s.ge, gt=s.gt, le=s.le, lt=s.lt)  # bounds apply to each element
        else:
            parse = inner if inner in (int, float, str) else str
        if canonical:
            deprecated_alias(g, generated, canonical[0], dest=name, default=None, type=parse)
        text = f"{s.doc} [{expected(hint, s)}; default {default!r}]" if default is not dataclasses.MISSING else s.doc
        text = text.replace("%", "%%")
        metavar = (metavars or {}).get(name)
        if hint is bool and flags[0].startswith("--no-"):
            g.add_argument(*flags, dest=name, action="store_false", default=None, help=f"turn off: {s.doc}")
        elif hint is bool:
            g.add_argument(*flags, dest=name, action=argparse.BooleanOptionalAction, default=None, help=text)
        elif many and name in repeatable:
            g.add_argument(*flags, dest=name, action="append", type=parse, default=None,
                           metavar=metavar or name.upper(), help=text + " (repeatable)")
        elif many:
            g.add_argument(*flags, dest=name, nargs="+", type=inner, default=None, metavar=metavar or name.upper(),
                           help=text)
        else:
            g.add_argument(*flags, dest=name, type=parse, default=None, help=text, choices=choices,
                           metavar=metavar or ((s.unit or name).upper() if inner in (int, float) else None))


def _not_none(hint):
    """``T`` for ``T | None``, else ``hint``."""
    import typing

    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if len(args) == 1 and len(typing.get_args(hint)) == 2 else hint


def _declared_type(cls, name, hint, s, inner):
    """An argparse ``type`` checking a flag's value against its setting's declaration (range, choices, pattern):
    a bad one is argparse's one line naming the flag, not an error from deep in the service's config."""

    def parse(text: str):
        from mntes_stream.core.settings import check_value, expected

        try:
            return check_value(cls, name, inner(text))
        except (ValueError, ConfigError):
            raise argparse.ArgumentTypeError(f"expected {expected(hint, s)}, got {text!r}") from None

    parse.__name__ = inner.__name__
    return parse


def settings_from_args(args, names) -> dict:
    """The settings among ``names`` given on the command line (lists of repeated or many values as tuples)."""
    return {n: tuple(v) if isinstance(v, list) else v for n in names if (v := getattr(args, n, None)) is not None}


def _replaced(cfg, flags: dict):
    """``cfg`` with ``flags``; a dict value replaces settings of the sub-settings of that name (``bridge``)."""
    return dataclasses.replace(cfg, **{k: _replaced(getattr(cfg, k), v) if isinstance(v, dict) else v
                                       for k, v in flags.items()})


def service_config(service_cls, path, sets, flags: dict, zenoh_flags):
    """A service's config: its file (``--config``) or its defaults, ``--set`` items, then flags, then zenoh flags.

    ``flags`` (:func:`settings_from_args`): settings of the service's config, and ``{table: {setting: value}}``
    for those of a sub-table (``{"bridge": {...}}``)."""
    from mntes_stream.service.config import config_of, with_zenoh

    return with_zenoh(with_flags(config_of(service_cls, path, sets), flags), zenoh_flags)


def with_flags(cfg, flags: dict):
    """``cfg`` with the settings given as flags (:func:`service_config`'s ``flags``) laid over it."""
    try:
        return _replaced(cfg, {k: v for k, v in flags.items() if v != {}})
    except ConfigError as exc:
        raise ConfigError(f"command line: {exc}") from None


def print_mapping(d: dict, as_json: bool, width: int = 24) -> None:
    """A command's result: one JSON object, or one right-aligned ``key: value`` per line (None skipped)."""
    import json

    if as_json:
        print(json.dumps(d, indent=2, default=str))
        return
    for key, value in d.items():
        if value is not None:
            print(f"{key:>{width}s}: {value}")


# ---------------------------------------------------------------------------- one grammar for every command
# docs/cli.md: --duration (s), --out, --set TABLE.KEY=VALUE, -q/--quiet, --overwrite, --json; old spellings
# stay as hidden aliases that say, in one line on stderr, what to write instead.


QUIET_HELP = "no progress (bars, start and per-second lines, info logs, detail); warnings, errors and the last line stay"


def add_quiet(p) -> None:
    """``-q``: one meaning for every command (docs/cli.md)."""
    p.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)


def add_json(p, what: str = "print the result as one JSON document") -> None:
    p.add_argument("--json", action="store_true", help=what)


def add_overwrite(p, what: str = "replace an existing output file") -> None:
    p.add_argument("--overwrite", action="store_true", help=what)


def claim_out(path, overwrite: bool, inputs=()) -> None:
    """Refuse an existing output unless ``--overwrite`` (then remove it first); never an input.

    Raises
    ------
    ConfigError
        The output exists without ``--overwrite``, is one of the inputs, or is a directory.
    """
    from pathlib import Path

    out = Path(path)
    if not out.exists():
        return
    if any(Path(i).exists() and out.resolve() == Path(i).resolve() for i in inputs):
        raise ConfigError(f"{out}: the output is one of the inputs")
    if not overwrite:
        raise ConfigError(f"{out} exists (--overwrite replaces it)")
    if out.is_dir():
        raise ConfigError(f"{out} is a directory: --overwrite replaces files only")
    out.unlink()


def setup_hint(zenoh, setup: str, timeout_s: float = 1.0) -> str | None:
    """One line naming a live setup close to ``setup`` (``--setup Lab`` when ``lab`` is live), else None.

    Asks zenoh for the setups' liveliness tokens (``mntes/<setup>/alive/**``)
    through a session that listens on nothing, so it never takes a port the
    command itself is about to listen on.
    """
    import dataclasses
    import difflib

    from mntes_stream.io import keys
    from mntes_stream.io.transport import open_session

    probe = dataclasses.replace(zenoh, listen=())
    setups: set[str] = set()
    try:
        with open_session(probe) as session:
            for reply in session.liveliness().get(f"{keys.PREFIX}/*/alive/**", timeout=timeout_s):
                if reply.ok is not None:
                    setups.add(str(reply.ok.key_expr).split("/")[1])
    except Exception:  # a hint only: whatever zenoh says, the command goes on
        return None
    if not setups or setup in setups:
        return None
    near = [s for s in setups if s.lower() == setup.lower()] or difflib.get_close_matches(setup, sorted(setups), n=1)
    live = ", ".join(sorted(setups))
    if near:
        return f"no service is live on setup {setup!r}; did you mean --setup {near[0]}? (live setups: {live})"
    return None
