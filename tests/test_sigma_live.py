"""Each sample's uncertainty through the converter pipeline (issue 26): sigma_P in every power chunk, equal to
core.uncertainty's on the same block, LOW_RESPONSIVITY flagged, the power itself unchanged."""

from __future__ import annotations

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.core.uncertainty import UncertaintySettings, noise_model, sigma_p_block
from mntes_stream.io.messages import CountsChunk, PowerChunk, Provenance
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.service.source import MinimalSource, SourceConfig


def _run(conv, msgs, uncertainty, sigma_p=True):
    pipe = ConverterPipeline(conv, PipelineConfig(setup="lab"), clock=None, uncertainty=uncertainty, sigma_p=sigma_p)
    out = []
    for t, batch in msgs:
        out += pipe.handle_many([(k, p, t) for k, p in batch])
    out += pipe.flush()
    return [(k, PowerChunk.from_bytes(p)) for k, p in out if "/power/" in k], pipe


def test_sigma_p_travels_with_the_power_and_flags_low_responsivity():
    # A tolerance of 1.01x the nominal sigma_P: the loading's swing takes part of each cycle beyond it.
    src = MinimalSource(SourceConfig(modules=2, channels=8, hwp_2f_amplitude_w=2e-13))
    msgs = list(src.batches(1_700_000_000_000_000_000, 2.0))
    params = {p.detector_id: p for p in src.params}
    conv = make_converter("table", params)
    settings = UncertaintySettings(sigma_p_factor=1.01)
    plain, _ = _run(conv, msgs, None)
    with_sigma, pipe = _run(conv, msgs, settings)
    assert len(plain) == len(with_sigma) == pipe.counters.chunks_converted > 0
    noise = noise_model(list(conv.params), settings)
    counts = {(c.board, c.module, c.seq): c for _, b in msgs for k, p in b if "/counts/" in k
              for c in [CountsChunk.from_bytes(p)]}
    low = 0
    for (_, a), (_, b) in zip(plain, with_sigma):
        assert a.sigma_p_w is None and b.sigma_p_w is not None and b.sigma_p_w.dtype == np.float32
        assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True)  # a warning bit: the power is the same
        assert np.array_equal(a.flags, b.flags & ~np.uint16(fl.LOW_RESPONSIVITY))
        usable = (b.flags & fl.UNUSABLE) == 0
        assert np.all(np.isfinite(b.sigma_p_w[usable])) and np.all(b.sigma_p_w[usable] > 0)
        low += int(np.count_nonzero(b.flags & fl.LOW_RESPONSIVITY))
        # The same sigma_P as core.uncertainty gives on that chunk converted alone (with the environment it had:
        # the pipeline's housekeeping is constant here, so the nominal environment of the chunk's samples).
        c = counts[(b.board, b.module, b.seq)]
        env = EnvironmentBlock(t_bath_k=np.full(c.n_samples, 0.1), b_field_t=np.zeros(c.n_samples))
        ids = list(b.detector_ids)
        blk = conv.convert(ids, c.counts_i, c.counts_q, env)
        ref = sigma_p_block(conv, ids, c.counts_i, c.counts_q, env, blk, noise)
        np.testing.assert_allclose(b.sigma_p_w[usable], ref.sigma_p_w[usable], rtol=2e-3)
    assert 0 < low  # part of the cycle is flagged
    # LOW_RESPONSIVITY alone (the default: in the conversion's own pass): the same flags, no sigma_P published.
    fused, _ = _run(conv, msgs, settings, sigma_p=False)
    assert len(fused) == len(with_sigma)
    for (_, a), (_, b) in zip(fused, with_sigma):
        assert a.sigma_p_w is None and np.array_equal(a.flags, b.flags)
        assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True)


def test_the_provenance_says_which_noise_was_used():
    from mntes_stream.io.messages import Provenance

    src = MinimalSource(SourceConfig(modules=1, channels=4))
    conv = make_converter("table", {p.detector_id: p for p in src.params})
    off = ConverterPipeline(conv, PipelineConfig(setup="lab"), clock=None)
    on = ConverterPipeline(conv, PipelineConfig(setup="lab"), clock=None, sigma_p=True,
                           uncertainty=UncertaintySettings(readout_noise_a=3e-12, sigma_p_factor=4.0))
    flag_only = ConverterPipeline(conv, PipelineConfig(setup="lab"), clock=None, uncertainty=UncertaintySettings())
    assert Provenance.from_bytes(off.provenance_bytes()).noise == {}
    noise = Provenance.from_bytes(on.provenance_bytes()).noise
    assert noise["readout_noise_a_setting"] == 3e-12 and noise["readout_noise_a_range"] == [3e-12, 3e-12]
    assert noise["low_responsivity"] == "sigma_P > 4 x nominal sigma_P" and noise["sigma_p_published"] is True
    noise = Provenance.from_bytes(flag_only.provenance_bytes()).noise
    assert noise["readout_noise_sources"] == {"default": 4} and noise["sigma_p_published"] is False


def test_offline_convert_takes_sigma_p_from_the_converter_config(tmp_path):
    """``convert REC OUT --config CONVERTER.toml`` with ``[converter] sigma_p = true``: sigma_P as that converter
    would publish it, the power the same as without; without a config, LOW_RESPONSIVITY by the defaults (on,
    factor 3), no sigma_P; with ``low_responsivity = "off"``, no LOW_RESPONSIVITY at all."""
    import subprocess
    import sys

    from mntes_stream.io.mcap import Session

    def cli(*args):
        res = subprocess.run([sys.executable, "-m", "mntes_stream", *args], cwd=tmp_path, capture_output=True,
                             text=True, timeout=300)
        assert res.returncode == 0, res.stderr
        return res

    cli("simulate", "--out", "rec.mcap", "--modules", "1", "--channels", "8", "--duration", "2")
    (tmp_path / "conv.toml").write_text('[converter]\nparams = "rec.params.toml"\nsigma_p = true\n'
                                        '[uncertainty]\nsigma_p_factor = 1.01\n')
    cli("convert", "rec.mcap", "with.mcap", "--params", "rec.params.toml", "--config", "conv.toml", "-q")
    cli("convert", "rec.mcap", "without.mcap", "--params", "rec.params.toml", "-q")
    (tmp_path / "off.toml").write_text('[converter]\nparams = "rec.params.toml"\nlow_responsivity = "off"\n')
    cli("convert", "rec.mcap", "off.mcap", "--params", "rec.params.toml", "--config", "off.toml", "-q")
    (tmp_path / "f3.toml").write_text('[converter]\nparams = "rec.params.toml"\nsigma_p = true\n')
    cli("convert", "rec.mcap", "f3.mcap", "--params", "rec.params.toml", "--config", "f3.toml", "-q")

    def power(name):
        msgs = list(Session(tmp_path / name).iter_messages())
        prov = [Provenance.from_bytes(m.payload) for m in msgs if m.topic.endswith("/provenance")]
        return [PowerChunk.from_bytes(m.payload) for m in msgs if "/power/" in m.topic], prov[-1]

    (w, prov_w), (wo, prov_wo), (off, prov_off), (f3, _) = (power(n) for n in ("with.mcap", "without.mcap",
                                                                              "off.mcap", "f3.mcap"))
    assert len(w) == len(wo) == len(off) == len(f3) > 0
    assert prov_w.noise["low_responsivity"] == "sigma_P > 1.01 x nominal sigma_P"
    assert prov_wo.noise["low_responsivity"] == "sigma_P > 3 x nominal sigma_P"
    assert prov_wo.noise["sigma_p_published"] is False and prov_off.noise == {}
    low = np.uint16(fl.LOW_RESPONSIVITY)
    for a, b, c, d in zip(w, wo, off, f3):
        assert b.sigma_p_w is None and c.sigma_p_w is None and a.sigma_p_w is not None
        assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True)
        assert np.array_equal(c.p_opt_w, b.p_opt_w, equal_nan=True)
        assert np.array_equal(a.flags & ~low, c.flags) and np.array_equal(b.flags & ~low, c.flags)
        assert not np.any(c.flags & low)
        assert np.array_equal(b.flags, d.flags)  # the default flags are those the sigma_P pass gives
        usable = (a.flags & fl.UNUSABLE) == 0
        assert np.all(a.sigma_p_w[usable] > 0) and np.all(np.isnan(a.sigma_p_w[~usable]))
