"""``jaxflex certify --params P.json [--vmax V] [--json]``: where a gain set is certified by the
N2 matrix of the paper's stability analysis (section 4, eq. 29-33; docs/spec.md section 4)."""

from __future__ import annotations

import argparse
import json

from jaxflex.io.presets import TRAJECTORIES


EXAMPLE = "jaxflex certify --params tuned.json --vmax 5 --bound"

def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``certify`` subcommand."""
    p = sub.add_parser(
        "certify",
        help="check the gains of a parameter file against the N2 stability certificate",
        description="Smallest eigenvalue of N2 (paper eq. 29) over link speeds 0..vmax and the "
        "largest speed up to which N2 stays positive definite (capped at vmax).",
    )
    p.add_argument("--params", required=True, help="parameter file with a 'gains' section")
    p.add_argument("--vmax", type=float, default=5.0,
                   help="end of the link-speed grid [rad/s] (default 5)")
    p.add_argument("--num", type=int, default=301, help="grid points (default 301)")
    p.add_argument("--margin", type=float, default=0.0,
                   help="require lambda_min(N2) > margin (default 0)")
    p.add_argument("--eps", type=float, default=1e-3,
                   help="eq. 30 tolerance eps [rad/s] (default 1e-3)")
    p.add_argument("--bound", action="store_true",
                   help="also report the ultimate bound of eq. 32-33")
    p.add_argument("--task", default="sinusoid", choices=TRAJECTORIES,
                   help="with --bound: the reference task whose speed range and half-range "
                   "give the bound in rad (default: sinusoid)")
    p.add_argument("--duration", type=float, default=10.0,
                   help="with --bound: seconds of the task (default 10)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Certify and print; exit 0 when N2 is positive definite over the whole grid, else 1."""
    from jaxflex.core.certificate import certify, task_bound, ultimate_bound
    from jaxflex.io.presets import trajectory_preset
    from jaxflex.io.params import load_params

    params = load_params(args.params)
    plant, gains = params.to_plant(), params.to_gains()
    res = certify(plant, gains, args.vmax, num=args.num, margin=args.margin, eps=args.eps)
    out = res.to_dict()
    if args.bound:
        out["ultimate_bound"] = ultimate_bound(plant, gains, args.vmax, num=args.num,
                                               eps=args.eps)
        out["task_bound"] = {"task": args.task, **task_bound(
            plant, gains, trajectory_preset(args.task), args.duration, num=args.num,
            eps=args.eps)}
    if args.json:
        print(json.dumps(out))
    else:
        state = "certified" if res.certified else "NOT certified"
        print(f"{state} over 0..{args.vmax:g} rad/s (margin {args.margin:g}): N2 positive "
              f"definite up to {res.certified_up_to:.4g} rad/s")
        print(f"lambda_min(N2): {out['lambda_min'][0]:.4g} at rest, "
              f"{out['lambda_min'][-1]:.4g} at {args.vmax:g} rad/s, min {out['min_lambda_min']:.4g}")
        if args.bound:
            b = out["ultimate_bound"]
            print(f"ultimate bound (eq. 32-33) over 0..{args.vmax:g} rad/s: ||rho|| <= "
                  f"D_bar/lambda_min = {b['D_bar']:.4g}/{b['lambda_min']:.4g} = "
                  f"{b['rho_bound']:.4g} (rho mixes rad, rad/s and eta; its e1 entry in rad)")
            tb = out["task_bound"]
            verdict = "VACUOUS" if tb["vacuous"] else "informative"
            print(f"task {args.task} (|q1'| <= {tb['task_speed']:.3g} rad/s): link error "
                  f"|e1| <= {tb['e1_bound_rad']:.4g} rad against a reference half-range of "
                  f"{tb['reference_half_range_rad']:.3g} rad: {verdict}; {tb['reason']}")
    return 0 if res.certified else 1
