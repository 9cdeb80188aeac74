"""Ground calibration (paper section 4), pure computation.

- ``measurements``: the six sweeps as data (``Sweep``, ``DetectorCalibration``, ``Campaign``);
- ``forward``: the measurement model (``predict_counts``), readout ``z(omega)``, parameter vector;
- ``simulate``: campaigns with known truth (``simulate_campaign``);
- ``fit``: per-detector joint fit with covariance and quality flags (``fit_detector``),
  the tabulated-transition outcome (``tabulated_transition``);
- ``campaign``: ``pulls`` against a truth (the parallel driver is ``mntes_stream.reports.calib_run``);
- ``endtoend``: HWP 2f -> 4f effective nonlinearity left by a calibration;
- ``lab``: the lab's IV and bias-step results (sotodlib det_cal, read by ``io.sotodlib_cal``)
  against the model's predictions (``compare``), and as a seed (``seed``: R_n, K from P_sat).
"""
