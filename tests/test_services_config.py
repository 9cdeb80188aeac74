"""The operator's files in services/ and the config mechanism: every file checks, layers and paths behave.

- every file in services/ passes ``mntes-stream config check`` (the real command);
- the converter and source configs agree (same detectors, the converter listens where the others connect);
- zenoh layering: defaults < JSON5 file (or $ZENOH_CONFIG) < [zenoh] table < flags, each layer only what it names;
- relative paths resolve against the config file, ``--set`` paths against the current directory;
- errors name the file, the table, the key and what was expected.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mntes_stream.errors import ConfigError
from mntes_stream.io.paramfile import load_params
from mntes_stream.io.transport import ZenohSettings, describe_config, zenoh_config
from mntes_stream.pipeline.build import build_converter
from mntes_stream.service.config import load_service_config, read_toml
from mntes_stream.service.converter import ConverterService, subscriptions
from mntes_stream.service.registry import SERVICES as REGISTRY
from mntes_stream.service.source import MinimalSource, default_params

SERVICES = Path(__file__).resolve().parents[1] / "services"


def _cli(*args, env=None, cwd=None):
    return subprocess.run([sys.executable, "-m", "mntes_stream", *map(str, args)], capture_output=True, text=True,
                          timeout=120, env=env, cwd=cwd)


def test_config_check_passes_on_every_file_in_services():
    files = sorted(p for p in SERVICES.iterdir() if p.suffix in (".toml", ".json5"))
    assert {"converter.toml", "source.toml", "simulator.toml", "recorder.toml", "replay.toml", "monitor.toml", "params.toml",
            "zenoh-lab.json5", "zenoh-local.json5", "zenoh-converter.json5", "zenoh-client.json5",
            "router.toml"} <= {p.name for p in files}
    res = _cli("config", "check", *files)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert len(lines) == len(files)
    for path, line in zip(files, lines):
        assert line.startswith(f"{path}: "), line
    # Each service file is named after the service it holds.
    for path in files:
        if path.suffix == ".toml" and path.name != "params.toml":
            service, _ = load_service_config(path)
            assert service.name == path.stem


def test_config_check_fails_with_one_line_per_bad_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[recorder]\nflush_interval_s = "1"\n')
    res = _cli("config", "check", SERVICES / "recorder.toml", bad, tmp_path / "missing.toml")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    errors = res.stderr.strip().splitlines()
    assert len(errors) == 2, errors
    assert f"{bad} [recorder] flush_interval_s: expected a number (s) > 0, got '1'" in errors[0]
    assert "missing.toml: no such file" in errors[1]


def test_config_show_prints_the_effective_config_with_defaults(capsys):
    res = _cli("config", "show", SERVICES / "converter.toml", "--set", "converter.kind=exact")
    assert res.returncode == 0, res.stderr
    import tomllib

    doc = tomllib.loads(res.stdout)  # valid TOML: it can be saved and used as a config
    assert doc["converter"]["kind"] == "exact"  # --set applied
    assert doc["converter"]["params"] == str(SERVICES / "params.toml")  # resolved against the file
    assert doc["alignment"]["hk_retention_s"] == 600.0  # a default the file does not name
    assert doc["status"]["interval_s"] == 1.0 and doc["zenoh"]["config_file"] == str(SERVICES / "zenoh-converter.json5")
    session = res.stdout.split("# the zenoh session this gives", 1)[1]
    assert "tcp/127.0.0.1:7447" in session and "peer" in session  # what the file says, as the session takes it
    # A template per registry service, loadable as it is printed. The command's own main in this process: one
    # interpreter start per service cost ~1-2 s each (12 services) and checked nothing the process boundary adds.
    from mntes_stream.cli import main

    for name in REGISTRY:
        capsys.readouterr()
        assert main(["config", "template", name]) == 0
        out = capsys.readouterr().out
        assert f"[{name}]" in out
        assert name in tomllib.loads(out)


def test_converter_and_source_configs_agree():
    _, conv = load_service_config(SERVICES / "converter.toml")
    _, src = load_service_config(SERVICES / "source.toml")
    assert conv.setup == src.source.setup == "lab"
    assert Path(conv.params) == Path(src.params) == SERVICES / "params.toml"
    # The converter listens where every other service connects (zenoh-local.json5).
    port = describe_config(zenoh_config(conv.zenoh))["listen/endpoints"][0].rsplit(":", 1)[1]
    assert port == "7447"
    for name in ("source.toml", "simulator.toml", "recorder.toml", "replay.toml", "monitor.toml"):
        _, cfg = load_service_config(SERVICES / name)
        eff = describe_config(zenoh_config(cfg.zenoh))
        assert any(e.endswith(":" + port) for e in eff["connect/endpoints"]), name
        assert eff["scouting/gossip/enabled"] is True and eff["scouting/multicast/enabled"] is False, name
        assert all(e.startswith("tcp/127.0.0.1:") for e in eff["listen/endpoints"]), name
    # Every detector the source publishes has parameters, and the file is the generated truth.
    params = load_params(conv.params)
    MinimalSource(src.source, list(params.values()))
    assert {p.detector_id: p.to_dict() for p in default_params(src.source)} == {k: p.to_dict() for k, p in params.items()}
    converter = build_converter(conv.spec).converter
    assert set(converter.detector_ids) == set(params)
    assert subscriptions(conv) == ["mntes/lab/hk/**", "mntes/lab/counts/*/*"]


def test_relative_paths_resolve_against_the_config_file(tmp_path, monkeypatch):
    other = tmp_path / "elsewhere"
    other.mkdir()
    monkeypatch.chdir(other)  # the current directory must not matter
    _, rec = load_service_config(SERVICES / "recorder.toml")
    assert rec.directory == str(SERVICES / "recordings")
    assert rec.zenoh.config_file == str(SERVICES / "zenoh-local.json5")
    _, rep = load_service_config(SERVICES / "replay.toml")
    assert rep.source == (str(SERVICES / "recordings"),)
    _, sim = load_service_config(SERVICES / "simulator.toml")
    assert sim.params_out == str(SERVICES / "simulator-params.toml")
    # A value given with --set is the command line's: relative to the current directory.
    _, rec = load_service_config(SERVICES / "recorder.toml", ["recorder.directory=out"])
    assert rec.directory == str(other / "out")
    _, rep = load_service_config(SERVICES / "replay.toml", ['replay.source=["a.mcap", "/abs/b.mcap"]'])
    assert rep.source == (str(other / "a.mcap"), "/abs/b.mcap")
    # An absolute path stays as it is.
    cfg = tmp_path / "c.toml"
    cfg.write_text('[recorder]\ndirectory = "/data/rec"\n')
    assert load_service_config(cfg)[1].directory == "/data/rec"


def _lab_file(tmp_path) -> Path:
    f = tmp_path / "z.json5"
    f.write_text("""// a site's zenoh file
{
  mode: "client",
  connect: { endpoints: ["tcp/192.0.2.1:7447"] },
  scouting: { multicast: { enabled: true }, gossip: { enabled: true } },
}
""")
    return f


def test_a_zenoh_file_is_honoured_exactly(tmp_path):
    f = _lab_file(tmp_path)
    eff = describe_config(zenoh_config(ZenohSettings(config_file=str(f))))
    # Nothing the file sets is overwritten by a built-in default (multicast included).
    assert eff == {"mode": "client", "connect/endpoints": ["tcp/192.0.2.1:7447"],
                   "listen/endpoints": eff["listen/endpoints"],
                   "scouting/multicast/enabled": True, "scouting/gossip/enabled": True}
    # A client does not get the loopback listen default (clients do not listen).
    assert eff["listen/endpoints"] != ["tcp/127.0.0.1:0"]


def test_zenoh_defaults_are_peer_loopback_and_no_scouting(monkeypatch):
    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    eff = describe_config(zenoh_config(ZenohSettings()))
    assert eff["mode"] == "peer" and eff["listen/endpoints"] == ["tcp/127.0.0.1:0"]
    assert eff["scouting/multicast/enabled"] is False and eff["scouting/gossip/enabled"] is False
    # Loopback in every mode unless listen is named: a router on zenoh's port, on 127.0.0.1.
    eff = describe_config(zenoh_config(ZenohSettings(mode="router", connect=("tcp/192.0.2.1:7447",))))
    assert eff["listen/endpoints"] == ["tcp/127.0.0.1:7447"]


def test_each_layer_overrides_only_what_it_names(tmp_path):
    f = _lab_file(tmp_path)
    table = ZenohSettings(config_file=str(f), mode="peer")  # a config's [zenoh] table naming the file and mode
    flags = ZenohSettings(connect=("tcp/127.0.0.1:1",), listen=("tcp/127.0.0.1:2",), multicast_scouting=False,
                          cfg=("scouting/gossip/enabled:false",))
    eff = describe_config(zenoh_config(flags.over(table)))
    assert eff == {"mode": "peer", "connect/endpoints": ["tcp/127.0.0.1:1"], "listen/endpoints": ["tcp/127.0.0.1:2"],
                   "scouting/multicast/enabled": False, "scouting/gossip/enabled": False}
    # A layer that names nothing leaves everything as it was.
    assert describe_config(zenoh_config(ZenohSettings().over(table))) == describe_config(zenoh_config(table))
    # One flag at a time over the file, the rest from the file.
    for layer, key, value in ((ZenohSettings(mode="peer"), "mode", "peer"),
                              (ZenohSettings(connect=("tcp/127.0.0.1:9",)), "connect/endpoints", ["tcp/127.0.0.1:9"]),
                              (ZenohSettings(multicast_scouting=False), "scouting/multicast/enabled", False),
                              (ZenohSettings(cfg=("mode:\"router\"",)), "mode", "router")):
        eff = describe_config(zenoh_config(layer.over(ZenohSettings(config_file=str(f)))))
        expected = describe_config(zenoh_config(ZenohSettings(config_file=str(f))))
        expected[key] = value
        if key == "mode":  # no longer a client, and the file names no listen: loopback only
            expected["listen/endpoints"] = [f"tcp/127.0.0.1:{7447 if value == 'router' else 0}"]
        assert eff == expected, (key, eff)


def test_zenoh_config_environment_variable_and_flag_precedence(tmp_path, monkeypatch):
    f = _lab_file(tmp_path)
    monkeypatch.setenv("ZENOH_CONFIG", str(f))
    assert describe_config(zenoh_config(ZenohSettings()))["mode"] == "client"
    other = tmp_path / "peer.json5"
    other.write_text('{ mode: "peer" }')
    # The file named by a config or -c wins over $ZENOH_CONFIG.
    assert describe_config(zenoh_config(ZenohSettings(config_file=str(other))))["mode"] == "peer"


def test_command_line_zenoh_flags_override_the_table(tmp_path):
    """The same flags as zenoh's example programs, through the real command (config show)."""
    res = _cli("config", "show", SERVICES / "recorder.toml")
    base = {line.split(" = ")[0].strip("# "): line.split(" = ")[1] for line in res.stdout.splitlines()
            if line.startswith("#   ")}
    assert base["connect/endpoints"] == '["tcp/127.0.0.1:7447"]'
    import tomllib

    from mntes_stream.cli import build_parser
    from mntes_stream.cli._common import zenoh_layer

    args = build_parser().parse_args(["serve", "--config", str(SERVICES / "recorder.toml"), "-m", "client",
                                      "-e", "tcp/127.0.0.1:5", "-l", "tcp/127.0.0.1:6", "--no-multicast-scouting",
                                      "--cfg", "scouting/gossip/enabled:false", "-c", str(_lab_file(tmp_path))])
    _, cfg = load_service_config(SERVICES / "recorder.toml")
    layered = zenoh_layer(args).over(cfg.zenoh)
    eff = describe_config(zenoh_config(layered))
    assert eff == {"mode": "client", "connect/endpoints": ["tcp/127.0.0.1:5"], "listen/endpoints": ["tcp/127.0.0.1:6"],
                   "scouting/multicast/enabled": False, "scouting/gossip/enabled": False}
    assert layered.file == str(tmp_path / "z.json5")  # -c replaces the table's file
    assert tomllib  # (TOML parsing of config show is checked above)


@pytest.mark.parametrize("doc, match", [
    ({"converter": {"params": "p.toml", "kind": "table", "colour": "red"}}, r"\[converter\]: unknown key\(s\) \['colour'\]"),
    ({"converter": {"params": "p.toml"}, "alignment": {"hk_staleness": 1.0}}, r"\[alignment\]: unknown key"),
    ({"converter": {"params": "p.toml"}, "status": {"every_s": 1.0}}, r"\[status\]: unknown key"),
    ({"converter": {"params": "p.toml", "boards": "0"}}, r"\[converter\] boards: expected a list of integers"),
    ({"converter": {"params": "p.toml", "kind": "tabel"}}, r"kind: expected one of 'table', 'grid'"),
    ({"converter": {}}, "give params"),
    ({"converter": {"params": "p.toml"}, "zenoh": {"mode": "satellite"}}, r"\[zenoh\] mode: expected one of 'peer'"),
    ({"converter": {"params": "p.toml"}, "zenoh": {"cfg": ["no-colon"]}}, "expected KEY:VALUE"),
    ({"converter": {"params": "p.toml"}, "extra": {}}, r"unknown table\(s\) \['extra'\]"),
    ({"converter": {"params": "p.toml", "zenoh": {}}}, r"zenoh goes in a table of its own"),
    ({"converter": {"params": "p.toml"}, "alignment": {"t_bath_range_k": [0.3, 0.1]}}, "increasing"),
])
def test_bad_converter_configs_name_file_table_key_and_expectation(tmp_path, doc, match):
    import tomli_w

    path = tmp_path / "conv.toml"
    path.write_text(tomli_w.dumps(doc))
    with pytest.raises(ConfigError, match=match) as exc:
        load_service_config(path)
    assert str(path) in str(exc.value)
    assert "\n" not in str(exc.value)


def test_a_config_names_exactly_one_service(tmp_path):
    path = tmp_path / "two.toml"
    path.write_text("[recorder]\n[replay]\n")
    with pytest.raises(ConfigError, match="exactly one of"):
        load_service_config(path)
    path.write_text("[zenoh]\n")
    with pytest.raises(ConfigError, match="exactly one of"):
        load_service_config(path)


def test_serve_runs_any_registry_service_and_errors_are_one_line(tmp_path):
    # A replay of an empty recording directory: serve finds the service by its table and runs it to its end.
    conf = tmp_path / "replay.toml"
    conf.write_text('[replay]\nsource = ["nothing-here"]\n')
    res = _cli("serve", "--config", conf, "-q")
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    res = _cli("serve", "--config", conf, "--duration", "1")
    assert res.returncode == 2 and "--duration does not apply to the replay service" in res.stderr
    res = _cli("serve", "--config", tmp_path / "missing.toml")
    assert res.returncode == 2 and "no such file" in res.stderr


def test_registry_is_the_one_list_of_services():
    from mntes_stream.service.base import Service

    # Services added by later modules (e.g. foxglove) join this list; each must keep the contract below.
    assert {"converter", "source", "simulator", "recorder", "replay", "monitor", "router"} <= set(REGISTRY)
    for name, cls in REGISTRY.items():
        assert issubclass(cls, Service) and cls.name == name and cls.summary
        # Each service's config builds from an empty document (defaults) or names what it needs.
        try:
            cfg = cls.config_from_document({})
        except ConfigError as exc:
            assert name == "converter" and "params" in str(exc)
            cfg = cls.config_from_document({name: {"params": "p.toml"}})
        assert isinstance(cfg, cls.Config) and hasattr(cfg, "zenoh")
        svc = cls(cfg)
        st = svc.status()
        assert st["service"] == name and st["state"] == "starting" and st["uptime_s"] >= 0
    with pytest.raises(ConfigError, match="unknown service 'nope'"):
        from mntes_stream.service.registry import service_class

        service_class("nope")


def test_params_file_errors_are_one_line(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text('schema = "mntes-params"\nversion = 1\n[defaults]\npreset = "table1"\n'
                 '[detectors.b0m0c000]\nt_c_k = "0.18"\n')
    res = _cli("config", "check", p)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "b0m0c000" in res.stderr and "t_c_k" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    env = {**os.environ}
    res = _cli("tables", "build", "--params", p, "--out", tmp_path / "t.npz", env=env)
    assert res.returncode == 2 and "Traceback" not in res.stderr and "t_c_k" in res.stderr


def test_read_toml_errors(tmp_path):
    bad = tmp_path / "x.toml"
    bad.write_text("[recorder\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        read_toml(bad)
    assert json.dumps(read_toml(SERVICES / "recorder.toml"))  # plain data
    assert ConverterService.name == "converter"
