"""``jaxflex analyse``: closed-loop modes of the sampled-data loop by autodiff (eigenvalues at
rest, Floquet multipliers over a period of the paper's sinusoid; ``jaxflex.loop.analyse``)."""

from __future__ import annotations

import argparse
import json

from jaxflex.core.controller import Q2D_METHODS
from jaxflex.io.presets import SENSING_PRESETS

EXAMPLE = "jaxflex analyse --q2d model --sensing ideal --floquet"


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``analyse`` subcommand."""
    p = sub.add_parser(
        "analyse",
        help="closed-loop modes (frequency, damping, participating states) by autodiff",
        description="Jacobian of the one-sample closed-loop map (plant step, observer, "
        "controller, velocity filters) at rest, its eigenvalues as modes (frequency [Hz], "
        "damping ratio, time constant [s], the states taking part); with --floquet also the "
        "monodromy multipliers over one period of the paper's sinusoid.",
    )
    p.add_argument("--params", help="parameter file (docs/spec.md section 7); default: the paper's")
    p.add_argument("--q2d", default="model", choices=Q2D_METHODS,
                   help="how the controller gets q2d' and q2d'' (default: model)")
    p.add_argument("--sensing", default="ideal", choices=SENSING_PRESETS,
                   help="which velocity path the loop has (quantisers act as identity); "
                   "default: ideal")
    p.add_argument("--no-compensation", action="store_true", help="observer off (F_hat = 0)")
    p.add_argument("--floquet", action="store_true",
                   help="also the Floquet multipliers along the paper's sinusoid")
    p.add_argument("--modes", type=int, default=6, help="modes to list (default 6)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Linearise and print the modes; exit 0 when every mode at rest decays, else 1."""
    from jaxflex.loop.analyse import analyse_loop
    from jaxflex.io.params import load_params
    from jaxflex.io.errors import InputError
    from jaxflex.io.presets import paper_params, sensing_preset

    if args.modes < 1:
        raise InputError(f"--modes must be >= 1, got {args.modes}")
    params = load_params(args.params) if args.params else paper_params()
    res = analyse_loop(params.to_plant(), params.to_gains(), q2d_method=args.q2d,
                       compensation=not args.no_compensation,
                       sensing=sensing_preset(args.sensing), floquet=args.floquet,
                       n_modes=args.modes)
    if args.json:
        print(json.dumps({**res.to_dict(), "sensing": args.sensing}))
        return 0 if res.rest.stable else 1
    for r, title in ((res.rest, "at rest (eigenvalues of the one-sample map)"),
                     (res.floquet, "along the sinusoid (monodromy multipliers)")):
        if r is None:
            continue
        print(f"{title}: spectral radius {r.spectral_radius:.6f} "
              f"({'stable' if r.stable else 'UNSTABLE'})")
        print(f"  {'|mu|':>9} {'f (Hz)':>8} {'damping':>8} {'tau (s)':>9}  states")
        for m in r.modes:
            st = ", ".join(f"{k} {v:.2f}" for k, v in m["states"].items())
            print(f"  {m['abs']:9.6f} {m['frequency_hz']:8.3f} {m['damping']:8.3f} "
                  f"{m['time_constant_s']:9.3g}  {st}")
    return 0 if res.rest.stable else 1
