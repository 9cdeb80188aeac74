"""The operator's files in services/: they parse, agree with each other, and build what they describe."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from mntes_stream.errors import ConfigError
from mntes_stream.io.paramfile import load_params
from mntes_stream.io.transport import ZenohSettings, zenoh_config
from mntes_stream.service.converter import ConverterConfig, build_converter, subscriptions
from mntes_stream.service.source import MinimalSource, SourceService, default_params

SERVICES = Path(__file__).resolve().parents[1] / "services"


def test_converter_and_source_configs_agree():
    conv = ConverterConfig.from_toml(SERVICES / "converter.toml")
    doc = tomllib.loads((SERVICES / "source.toml").read_text())
    src = SourceService.from_dict(doc, "source.toml", base_dir=SERVICES)
    assert conv.setup == src.source.setup == "lab"
    assert Path(conv.params) == Path(src.params) == SERVICES / "params.toml"
    # The converter listens where the source (and recorder, replay) connect.
    port = conv.zenoh.listen[0].rsplit(":", 1)[1]
    for name in ("source.toml", "recorder.toml", "replay.toml"):
        z = tomllib.loads((SERVICES / name).read_text())["zenoh"]
        assert any(e.endswith(":" + port) for e in z["connect"]), name
        assert z.get("gossip") is True, name
    # Every detector the source publishes has parameters, and the file is the generated truth.
    params = load_params(conv.params)
    MinimalSource(src.source, list(params.values()))
    assert {p.detector_id: p.to_dict() for p in default_params(src.source)} == {k: p.to_dict() for k, p in params.items()}
    converter = build_converter(conv)
    assert set(converter.detector_ids) == set(params)
    assert subscriptions(conv) == ["mntes/lab/hk/**", "mntes/lab/counts/*/*"]


def test_every_service_file_the_docs_name_exists_and_loads():
    from mntes_stream.cli.serve import _load
    from mntes_stream.service.recorder import RecorderConfig
    from mntes_stream.service.replay import ReplayConfig

    readme = (SERVICES.parent / "README.md").read_text()
    table = [line for line in (SERVICES / "README.md").read_text().splitlines() if line.startswith("| `")]
    named = set(re.findall(r"services/([a-z][\w.-]*\.(?:toml|json5))", readme + (SERVICES / "README.md").read_text()))
    named |= {re.match(r"\| `([^`]+)`", line).group(1) for line in table}
    assert {"converter.toml", "source.toml", "recorder.toml", "replay.toml"} <= named
    for name in named:
        assert (SERVICES / name).is_file(), f"{name} is documented but not in services/"
    build = {"converter": lambda doc, path: ConverterConfig.from_dict(doc, str(path), base_dir=SERVICES),
             "source": lambda doc, path: SourceService.from_dict(doc, str(path), base_dir=SERVICES),
             "recorder": lambda doc, path: RecorderConfig.from_dict(doc, str(path), base_dir=str(SERVICES)),
             "replay": lambda doc, path: ReplayConfig.from_toml(path, source=("x.mcap",))}
    for path in sorted(SERVICES.glob("*.toml")):
        if path.name == "params.toml":
            continue
        kind, doc = _load(str(path))
        assert kind == path.stem, f"{path.name} holds a [{kind}] service"  # the file is named after its service
        build[kind](doc, path)


def test_lab_zenoh_config_loads_and_keeps_multicast_off():
    z = ZenohSettings(config_file=str(SERVICES / "zenoh-lab.json5"))
    conf = zenoh_config(z)
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert '"wait_before_close":30000000' in conf.get_json("transport/link/tx/queue/congestion_control")
    # The service's own settings override the file.
    conf = zenoh_config(ZenohSettings(config_file=z.config_file, connect=("tcp/127.0.0.1:1",), gossip=True))
    assert conf.get_json("connect/endpoints") == '["tcp/127.0.0.1:1"]'


@pytest.mark.parametrize(
    "doc",
    [
        {"converter": {"params": "p.toml", "kind": "table", "colour": "red"}},
        {"converter": {"params": "p.toml"}, "alignment": {"hk_staleness": 1.0}},
        {"converter": {"params": "p.toml"}, "status": {"every_s": 1.0}},
        {"converter": {"params": "p.toml", "boards": "0"}},
        {"converter": {}},
        {"converter": {"params": "p.toml"}, "zenoh": {"mode": "satellite"}},
        {"converter": {"params": "p.toml"}, "extra": {}},
    ],
)
def test_bad_converter_configs_raise_config_error(doc):
    with pytest.raises(ConfigError):
        ConverterConfig.from_dict(doc)
