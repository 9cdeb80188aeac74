"""One grammar for every command (docs/cli.md): grouped help, one spelling per flag, help on every flag,
options that do not apply are errors, exit codes as documented. Each check runs the real parser or the real
command in a subprocess; none needs zenoh, a network or an extra beyond the base install (G3 ones skip)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from mntes_stream.cli import GROUPS, build_parser, main

ROOT = Path(__file__).resolve().parents[1]
SERVICES = ROOT / "services"

# The grammar: a flag that means one of these is spelled this way (docs/cli.md). Each wrong spelling may
# exist only as a hidden alias (help suppressed), which says the right one when used.
WRONG = {"--duration-s": "--duration", "--mcap": "--out", "--force": "--overwrite", "--output": "--out",
         "--quiet-mode": "-q"}


def _walk(parser, path=()):
    """``(command path, action)`` of every argument of every (sub)command."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _walk(sub, (*path, name))
        else:
            yield path, action


def test_every_flag_has_help_and_wrong_spellings_are_hidden_aliases():
    missing, visible = [], []
    for path, action in _walk(build_parser()):
        if isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            continue
        where = f"{' '.join(path)} {'/'.join(action.option_strings) or action.dest}"
        if not action.help:
            missing.append(where)
        if action.help is not argparse.SUPPRESS and set(action.option_strings) & set(WRONG):
            visible.append(where)
    assert not missing, f"flags without help: {missing}"
    assert not visible, f"a wrong spelling shown in help (make it a hidden deprecated alias): {visible}"


def test_quiet_is_dash_q_everywhere_and_writers_take_overwrite():
    from mntes_stream.cli._common import QUIET_HELP

    for path, action in _walk(build_parser()):
        if "--quiet" in action.option_strings or "-q" in action.option_strings:
            assert "-q" in action.option_strings, f"{' '.join(path)}: --quiet without -q"
            # -q means one thing (issue 34: it meant three): cli._common.add_quiet, one help text.
            assert action.help == QUIET_HELP, f"{' '.join(path)}: -q says {action.help!r}"
    writers = {("convert",), ("recover",), ("simulate",), ("export",), ("transcode",), ("params",),
               ("tables", "build"), ("calib", "simulate"), ("calib", "fit")}
    has = {path for path, action in _walk(build_parser()) if "--overwrite" in action.option_strings}
    assert writers <= has, f"commands writing a file without --overwrite: {sorted(writers - has)}"


def test_help_lists_every_command_in_a_group(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    placed = {c for cs in GROUPS.values() for c in cs}
    assert set(sub.choices) <= placed, f"commands in no group (cli/__init__.py GROUPS): {set(sub.choices) - placed}"
    titles = [line for line in text.splitlines() if line.endswith(":") and not line.startswith(" ")]
    assert titles[:5] == ["operate:", "record and replay:", "export:", "calibrate and validate:", "develop:"]
    assert "other:" not in titles
    for name in sub.choices:
        assert f"\n  {name} " in text, name


def test_serve_help_lists_every_registered_service(capsys):
    from mntes_stream.service.registry import SERVICES as REGISTRY

    with pytest.raises(SystemExit):
        main(["serve", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in REGISTRY:
        assert f"[{name}]" in text, name


def test_config_check_of_the_services_directory_as_documented(tmp_path, capsys):
    """services/README.md: `mntes-stream config check services/*` (README, grafana/, secure/ included)."""
    import glob

    assert main(["config", "check", *sorted(glob.glob(str(SERVICES / "*")))]) == 0
    res = capsys.readouterr()
    assert not res.err and "README.md: skipped" in res.out and "grafana: skipped" in res.out
    assert "secure/zenoh-router.json5: zenoh config" in res.out and "converter.toml: converter" in res.out
    assert main(["config", "check", str(SERVICES)]) == 0  # a directory: its configs and nothing else
    out = capsys.readouterr().out
    assert "README" not in out and "recorder.toml: recorder" in out
    (tmp_path / "bad.toml").write_text('[recorder]\nflush_interval_s = "1"\n')
    (tmp_path / "notes.txt").write_text("not a config\n")
    assert main(["config", "check", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"mntes-stream: error: {tmp_path / 'bad.toml'} [recorder] flush_interval_s: expected a number (s) > 0, "
        "got '1'"]
    assert main(["config", "check", str(tmp_path / "missing.toml")]) == 2
    assert main(["config", "check", str(SERVICES / "recorder.toml"), "--set", "recorder.fsync=true"]) == 2
    assert "--set applies to config show" in capsys.readouterr().err


def test_an_option_that_does_not_apply_is_an_error(tmp_path, capsys):
    rec = tmp_path / "rec.mcap"
    rec.write_bytes(b"")  # never read: the options are refused first
    for argv, says in (
            (["convert", str(tmp_path / "run.g3"), str(tmp_path / "o.mcap"), "--kind", "linear"],
             "--kind does not apply to RUN.g3 -> OUT.mcap"),
            (["convert", str(rec), str(tmp_path / "o.mcap"), "--setup", "x", "--wiring", "w.g3"],
             "--wiring, --setup do not apply"),
            (["simulate", "--out", str(tmp_path / "s.mcap"), "--duration", "1", "--layout", "timepoints"],
             "--layout apply to --format g3 only"),
            (["config", "template", "recorder", "--set", "recorder.fsync=true"], "--set applies to config show"),
            (["simulate", "--out", str(tmp_path / "s.mcap"), "--duration", "1", "--speed", "2"],
             "--speed is for live publication"),
            (["simulate", "--out", str(tmp_path / "s.mcap"), "--duration", "1", "--error-scale", "2"],
             "--error-scale/--error-seed need --perturbed-params-out"),
            (["tables", "build", "--params", "p.toml", "--out", "t.npz", "--n-power", "64"],
             "--n-power: not for --kind table"),
            (["export", str(rec), "--out", str(tmp_path / "e"), "--format", "toast", "--compression", "lzf"],
             "--compression is not for --format toast"),
            (["export", str(rec), "--out", str(tmp_path / "e"), "--format", "sotodlib", "--block-samples", "64"],
             "--block-samples is for --format hdf5")):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], (argv, err)


def test_outputs_are_refused_without_overwrite_and_replaced_with_it(tmp_path, capsys):
    out = tmp_path / "s.mcap"
    argv = ["simulate", "--out", str(out), "--duration", "0.3", "--modules", "1", "--channels", "2", "-q", "--json"]
    assert main(argv) == 0
    size = out.stat().st_size
    capsys.readouterr()
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == f"mntes-stream: error: {out} exists (--overwrite replaces it)"
    assert out.stat().st_size == size
    assert main([*argv, "--overwrite", "--seed", "3"]) == 0 and out.exists()
    capsys.readouterr()
    assert main(["convert", str(out), str(out), "--overwrite"]) == 2  # never the input
    assert "the output is one of the inputs" in capsys.readouterr().err and out.stat().st_size > 0
    # export's writers are a Python API too (overwrite=True); the command speaks shell (issue 34).
    h5 = tmp_path / "power.h5"
    h5.write_bytes(b"kept")
    for fmt in ("hdf5", "toast"):
        assert main(["export", str(out), "--out", str(h5), "--format", fmt]) == 2
        assert capsys.readouterr().err.strip() == f"mntes-stream: error: {h5} exists (--overwrite replaces it)"
    assert h5.read_bytes() == b"kept"


def test_old_spellings_still_work_with_one_line(tmp_path, capsys):
    out = tmp_path / "old.mcap"
    assert main(["simulate", "--mcap", str(out), "--duration", "0.3", "--modules", "1", "--channels", "2",
                 "--set", "latched_per_module=0", "-q"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "deprecated" in line]
    assert warnings == ["mntes-stream: warning: --mcap is deprecated; use --out",
                        "mntes-stream: warning: --set latched_per_module=0: KEY=VALUE is deprecated; use "
                        "simulator.latched_per_module=0"]
    assert out.exists()
    args = build_parser().parse_args(["record", "--duration-s", "3"])
    assert args.duration_s == 3.0 and "--duration-s is deprecated; use --duration" in capsys.readouterr().err
    args = build_parser().parse_args(["record", "--directory", "d"])
    assert args.directory == "d" and "--directory is deprecated; use --out" in capsys.readouterr().err
    assert build_parser().parse_args(["record", "--out", "o"]).directory == "o"


def test_simulate_set_takes_table_key_value(tmp_path, capsys):
    out = tmp_path / "s.mcap"
    assert main(["simulate", "--out", str(out), "--duration", "0.3", "--modules", "1", "--channels", "3",
                 "--set", "simulator.latched_per_module=0", "--set", "simulator.saturated_per_module=0",
                 "--set", "simulator.channels=2", "-q", "--json"]) == 0
    import json

    # A flag wins over --set, as for every service (cli._common.service_config); before, simulate alone had --set win.
    assert json.loads(capsys.readouterr().out)["detectors"] == 3
    assert main(["simulate", "--out", str(tmp_path / "t.mcap"), "--duration", "0.3",
                 "--set", "simulator.no_such_key=1"]) == 2
    assert "no_such_key" in capsys.readouterr().err


def test_a_misspelt_setup_gets_the_live_one_suggested(capsys):
    """`--setup Lab` while `lab` is live: one line naming it (ps, monitor), over a real loopback zenoh session."""
    from mntes_stream.io.transport import free_tcp_port, loopback, open_session

    port = free_tcp_port()
    with open_session(loopback(port)) as session:
        token = session.liveliness().declare_token("mntes/lab/alive/converter/test")
        try:
            assert main(["ps", "--setup", "Lab", "-e", f"tcp/127.0.0.1:{port}", "--interval", "0"]) == 0
            err = capsys.readouterr().err.strip().splitlines()
            assert err == ["mntes-stream: warning: no service is live on setup 'Lab'; did you mean --setup lab? "
                           "(live setups: lab)"], err
            assert main(["monitor", "--setup", "Lab", "--text", "--duration", "0.5", "--update-s", "0.2",
                         "-e", f"tcp/127.0.0.1:{port}"]) == 0
            assert "did you mean --setup lab?" in capsys.readouterr().err
            assert main(["ps", "--setup", "lab", "-e", f"tcp/127.0.0.1:{port}", "--interval", "0"]) == 0
            assert "did you mean" not in capsys.readouterr().err
        finally:
            token.undeclare()


def test_docs_cli_lists_every_command_and_every_overwrite():
    """docs/cli.md: the command table in --help's groups, and the commands taking --overwrite."""
    text = (ROOT / "docs" / "cli.md").read_text()
    table = text.split("## Commands", 1)[1].split("\n## ", 1)[0]
    group = None
    where = {}
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[1].startswith("`"):
            group = cells[0] or group
            where[cells[1].strip("`")] = group
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name in sub.choices:
        title = next(g for g, cs in GROUPS.items() if name in cs)
        assert where.get(name) == title, f"docs/cli.md: {name} not listed under {title!r}"
    row = next(line for line in text.splitlines() if line.startswith("| `--overwrite`"))
    for path, action in _walk(build_parser()):
        if "--overwrite" in action.option_strings:
            assert f"`{' '.join(path)}`" in row, f"docs/cli.md: --overwrite row misses {' '.join(path)}"


def test_service_flags_come_from_the_settings_they_set_with_their_spellings(tmp_path, capsys):
    """dfmux-bridge, g3-bridge, simulate and monitor declare their flags from the settings (``add_settings_args``): each
    flag, spelled as before, sets its setting over ``--config`` and ``--set`` (simulate too, since it laid its flags
    under ``--set``), and is checked at parse time against the declaration (one line naming the flag)."""
    from mntes_stream.cli.dfmux import bridge_config
    from mntes_stream.cli.monitor import monitor_config
    from mntes_stream.cli.simulate import _config as simulate_config

    parser = build_parser()
    cfg = tmp_path / "bridge.toml"
    cfg.write_text('[dfmux-bridge]\nchunk_samples = 8\nhk_timeout_s = 1.5\nboards = [9]\n')
    b = bridge_config(parser.parse_args(
        ["dfmux-bridge", "--config", str(cfg), "--set", "dfmux-bridge.hk_stale_s=7", "--board", "3", "--board", "4",
         "--v2-board", "10.0.0.2=5", "--sctp", "h1", "--sctp", "h2", "--bias", "3/0=1e-6", "--hk-every", "2",
         "--no-board-hk", "--duration", "3", "--t-bath-k", "0.1", "-e", "tcp/127.0.0.1:7447"])).bridge
    assert (b.boards, b.v2_boards, b.sctp, b.bias) == ((3, 4), ("10.0.0.2=5",), ("h1", "h2"), ("3/0=1e-6",))
    assert (b.hk_every_s, b.board_hk, b.duration_s, b.t_bath_k) == (2.0, False, 3.0, 0.1)
    assert (b.chunk_samples, b.hk_timeout_s, b.hk_stale_s, b.board_names) == (8, 1.5, 7.0, True)  # file, --set, default
    s = simulate_config(parser.parse_args(
        ["simulate", "--modules", "3", "--sample-rate", "19.1", "--f-hwp", "1.5", "--duration", "2", "--chunk-s",
         "0.2", "--speed", "0", "--setup", "x1", "--seed", "4", "--set", "simulator.seed=5", "-e", "tcp/127.0.0.1:1"]))
    assert (s.sim.modules, s.sim.sample_rate_hz, s.sim.f_hwp_hz, s.sim.seed) == (3, 19.1, 1.5, 4)
    assert (s.duration_s, s.chunk_s, s.speed, s.setup) == (2.0, 0.2, 0.0, "x1")
    # --set still sets what no flag gives, with or without --config; --config's file is below both.
    cfg.write_text('[simulator]\nmodules = 5\nseed = 9\nchunk_s = 0.5\n')
    s = simulate_config(parser.parse_args(["simulate", "--config", str(cfg), "--set", "simulator.seed=5", "--modules", "2"]))
    assert (s.sim.modules, s.sim.seed, s.chunk_s) == (2, 5, 0.5)
    s = simulate_config(parser.parse_args(["simulate", "--set", "simulator.channels=7", "--telescope", "MFT"]))
    from mntes_stream.core.sim import HWP_FREQUENCIES_HZ

    assert (s.sim.channels, s.sim.f_hwp_hz) == (7, HWP_FREQUENCIES_HZ["MFT"])
    from mntes_stream.cli.ocs import bridge_config as ocs_config

    o = ocs_config(parser.parse_args(["ocs-bridge", "--router", "ws://h:1/ws", "--t-bath-field", "a.b.c", "--stale-s",
                                      "3", "--duration", "2", "--realm", "r"])).bridge
    assert (o.router, o.t_bath_field, o.stale_s, o.duration_s, o.realm, o.setup) == ("ws://h:1/ws", "a.b.c", 3.0,
                                                                                     2.0, "r", "lab")
    from mntes_stream.cli.g3 import bridge_config as g3_config

    cfg.write_text('[g3-bridge]\nchunk_samples = 8\nboards = [9]\n[g3]\nt_bath_default_k = 0.3\n')
    g = g3_config(parser.parse_args(["g3-bridge", "--config", str(cfg), "--from", "run.g3", "--board", "3", "--board",
                                     "4", "--duration", "2", "--t-bath-key", "A.B", "--set", "g3-bridge.setup=x2"]))
    assert (g.bridge.source, g.bridge.boards, g.bridge.duration_s, g.bridge.chunk_samples, g.bridge.setup) == (
        "run.g3", (3, 4), 2.0, 8, "x2")
    assert (g.g3.t_bath_key, g.g3.t_bath_default_k) == ("A.B", 0.3)
    # replay: --speed, --topics and --wait-s set their [replay] settings over the file, --afap and --all theirs.
    from mntes_stream.cli.record import replay_config

    cfg.write_text('[replay]\nspeed = 3.0\nwait_subscribers_s = 7.0\ntopics = ["x/**"]\n')
    r = replay_config(parser.parse_args(["replay", "a.mcap", "--config", str(cfg), "--speed", "4", "--topics", "a/**",
                                         "b", "--wait-s", "2"]))
    assert (r.source, r.speed, r.topics, r.wait_subscribers_s) == (("a.mcap",), 4.0, ("a/**", "b"), 2.0)
    r = replay_config(parser.parse_args(["replay", "--config", str(cfg)]))
    assert (r.speed, r.topics, r.wait_subscribers_s) == (3.0, ("x/**",), 7.0)  # the file's, where no flag is given
    r = replay_config(parser.parse_args(["replay", "a.mcap", "--afap", "--all"]))
    assert (r.speed, r.topics, r.wait_subscribers_s) == (0.0, ("**",), 5.0)
    # convert and params read a G3 file with the same [g3] settings, from the same declarations (G3InputConfig).
    from mntes_stream.cli.g3 import g3_input_config
    from mntes_stream.g3.settings import G3InputConfig

    given = ["--t-bath-key", "A.B", "--t-bath-unit", "mK", "--t-bath-default-k", "0.25", "--b-field-t", "-0.00002"]
    for argv in (["convert", "run.g3", "out.mcap", *given],
                 ["params", "--from", "run.g3", "--params", "p.toml", "--out", "o.toml", *given]):
        assert g3_input_config(parser.parse_args(argv)) == G3InputConfig(
            t_bath_key="A.B", t_bath_unit="mK", t_bath_default_k=0.25, b_field_t=-2e-5), argv
    assert g3_input_config(parser.parse_args(["convert", "run.g3", "out.mcap"])) == G3InputConfig()
    helps = {path: action.help for path, action in _walk(parser) if "--t-bath-unit" in action.option_strings}
    assert set(helps) == {("convert",), ("params",)} and len(set(helps.values())) == 1, helps
    from mntes_stream.core.settings import declared

    assert declared(G3InputConfig.__dataclass_fields__["t_bath_unit"]).doc in helps[("convert",)]
    m = monitor_config(parser.parse_args(["monitor", "--port", "0", "--history-s", "20", "--f-hwp", "auto",
                                          "--update-s", "2"]))
    assert (m.port, m.view.history_s, m.view.f_hwp_hz, m.update_s) == (0, 20.0, None, 2.0)
    for argv, says in ((["dfmux-bridge", "--board", "-1"], "argument --board: expected an integer >= 0, got '-1'"),
                       (["dfmux-bridge", "--hk-every", "0"], "argument --hk-every: expected a number (s) > 0"),
                       (["simulate", "--sample-rate", "0"], "argument --sample-rate: expected a number (Hz) > 0"),
                       (["g3-bridge", "--chunk-samples", "0"], "argument --chunk-samples: expected an integer >= 1"),
                       (["simulate", "--setup", "a/b"], "argument --setup: expected a name matching"),
                       (["replay", "--wait-s", "-1"], "argument --wait-s: expected a number (s) >= 0"),
                       (["replay", "--speed", "2", "--afap"], "argument --afap: not allowed with argument --speed")):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)
        assert says in capsys.readouterr().err, argv
