"""``mntes-stream model``: one detector's operating point, Table 1 style."""

from __future__ import annotations

import json

from mntes_stream.cli._common import add_params_args, params_from_args
from mntes_stream.options import number

_ROWS = [
    ("Optical loading", "p_opt_w", 1e12, "pW"),
    ("Bath temperature", "t_bath_k", 1e3, "mK"),
    ("Thevenin voltage (RMS)", "v_thev_v", 1e6, "uV"),
    ("Operating resistance", "r_ohm", 1.0, "Ohm"),
    ("Fractional resistance", "r_frac", 1.0, ""),
    ("TES temperature", "t_tes_k", 1e3, "mK"),
    ("TES current (peak)", "i_peak_a", 1e6, "uA"),
    ("Electrical power", "p_electrical_w", 1e12, "pW"),
    ("Saturation power", "p_sat_w", 1e12, "pW"),
    ("Loop gain L", "loop_gain", 1.0, ""),
    ("alpha", "alpha", 1.0, ""),
    ("beta", "beta", 1.0, ""),
    ("|Responsivity| (eq. 3)", "abs_responsivity_a_per_w", 1e-6, "1e6 A/W"),
    ("G-bar = P_sat/(T_c - T_bath)", "g_bar_w_per_k", 1e12, "pW/K"),
    ("G = n K T^(n-1)", "g_dynamic_w_per_k", 1e12, "pW/K"),
    ("tau0 = C/G", "tau0_s", 1e3, "ms"),
    ("tau_eff = tau0/(1+L)", "tau_eff_s", 1e3, "ms"),
    ("|d2I/dP2|", "d2i_dp2_a_per_w2", 1e-18, "1e18 A/W^2"),
    ("Nonlinearity |d2I/dP2|/|S|", "nonlinearity_per_pw", 1.0, "1/pW"),
]


def run(args) -> int:
    from mntes_stream.core.model import describe, tune_bias_v

    p = params_from_args(args)
    v = None
    if args.tune_r_frac is not None:
        v = float(tune_bias_v(p, args.tune_r_frac, p_opt_w=args.p_opt_w, t_bath_k=args.t_bath_k))
    elif args.v_thev_v is not None:
        v = args.v_thev_v
    d = describe(p, p_opt_w=args.p_opt_w, t_bath_k=args.t_bath_k, b_field_t=args.b_field_t, v_thev_v=v)
    if args.figure:
        from mntes_stream.reports.plots import figure_parameter_dependence

        figure_parameter_dependence(p, args.figure)
    if args.response_figure:
        from mntes_stream.reports.plots import figure_response_function

        figure_response_function(p, args.response_figure, r_frac=args.tune_r_frac)
    if args.json:
        print(json.dumps(d, indent=2))
        return 0
    print(f"MNTES model: detector {d['detector_id']} ({d['units']})")
    for label, key, scale, unit in _ROWS:
        print(f"  {label:<32s} {d[key] * scale:>12.4g} {unit}")
    for path in (args.figure, args.response_figure):
        if path:
            print(f"wrote {path}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("model", help="print a detector's assumed and derived parameters (paper Table 1)")
    add_params_args(p)
    p.add_argument("--tune-r-frac", type=number(float, gt=0, lt=1), metavar="X", help="re-tune the bias to R = X R_n first")
    p.add_argument("--v-thev-v", type=number(float, "V", gt=0), metavar="V", help="bias voltage (RMS, volts) instead of the file's")
    p.add_argument("--p-opt-w", type=number(float, "W", ge=0), metavar="W", help="optical loading (default: the detector's nominal)")
    p.add_argument("--t-bath-k", type=number(float, "K", gt=0), metavar="K", help="bath temperature (default: nominal)")
    p.add_argument("--b-field-t", type=number(float, "T"), default=0.0, metavar="T", help="magnetic field (default 0)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--figure", metavar="PNG", help="write paper Figure 1 (parameter dependence)")
    p.add_argument("--response-figure", metavar="PNG", help="write paper Figure 2 (response and inverse)")
    p.set_defaults(func=run)
