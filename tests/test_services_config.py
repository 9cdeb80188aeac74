"""The operator's files in services/: they parse, agree with each other, and build what they describe."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from mntes_stream.errors import ConfigError
from mntes_stream.io.paramfile import load_params
from mntes_stream.io.transport import ZenohSettings, zenoh_config
from mntes_stream.service.converter import ConverterConfig, build_converter, subscriptions
from mntes_stream.service.source import MinimalSource, SourceService, default_params

SERVICES = Path(__file__).resolve().parents[1] / "services"


def test_converter_and_simulator_configs_agree():
    conv = ConverterConfig.from_toml(SERVICES / "converter.toml")
    doc = tomllib.loads((SERVICES / "simulator.toml").read_text())
    src = SourceService.from_dict(doc, "simulator.toml", base_dir=SERVICES)
    assert conv.setup == src.source.setup == "lab"
    assert Path(conv.params) == Path(src.params) == SERVICES / "params.toml"
    # The converter listens where the simulator (and recorder, replay) connect.
    port = conv.zenoh.listen[0].rsplit(":", 1)[1]
    for name in ("simulator.toml", "recorder.toml", "replay.toml"):
        z = tomllib.loads((SERVICES / name).read_text())["zenoh"]
        assert any(e.endswith(":" + port) for e in z["connect"]), name
        assert z.get("gossip") is True, name
    # Every detector the simulator publishes has parameters, and the file is the generated truth.
    params = load_params(conv.params)
    MinimalSource(src.source, list(params.values()))
    assert {p.detector_id: p.to_dict() for p in default_params(src.source)} == {k: p.to_dict() for k, p in params.items()}
    converter = build_converter(conv)
    assert set(converter.detector_ids) == set(params)
    assert subscriptions(conv) == ["mntes/lab/hk/**", "mntes/lab/counts/*/*"]


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
