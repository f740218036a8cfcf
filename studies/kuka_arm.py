"""Study: does the KUKA KR300's axes 1-3 identified as one coupled rigid-body arm (IDIM-WLS,
``jaxflex.identify.arm``) predict the motor torques of the validation trajectories better than
the rigid least-squares model of each axis alone?

Model (``jaxflex.identify.arm`` docstring): the six-axis chain of ``jaxflex.data.kr300`` (axes
4-6 at their measured motor-encoder motion, or held at their mean angle for comparison), link
angles of axes 1-3 from the link encoders, per joint a rotor inertia on the motor
acceleration, viscous and Coulomb friction on the motor velocity and a torque offset, and the
hydraulic counterbalance of axis 2 known (scale 1; its fitted scale is reported). Fitted on A,
validated on B and C with the error ``100 ||tau - tau_hat|| / ||tau||`` per axis over all
samples (``jaxflex.validate.rel_error_pct``), as ``studies/kuka_flexible.py`` computes it.

Variants, all fitted on A only:

- ``nominal``: the base parameters held at the shipped model's inertias, only the per-joint
  terms fitted (12 parameters): the headline, ``coupled`` in the JSON.
- ``full``: every structural base parameter free (plain IDIM-WLS).
- ``essential``: backward elimination to the base parameters with relative standard error
  below 10 % on A, the rest at the shipped values.
- ``consistent``: the full fit refitted with physically consistent links (log-Cholesky), and
  whether the plain estimate's confidence region holds a physical arm.
- ``nominal_wrist_held`` and ``nominal_fitted_counterbalance``: the headline with the wrist
  held, and with the counterbalance's scale fitted.

Baseline ``per_axis``: ``jaxflex.validate.rigid_torque_fit`` on A per axis (motor encoder).

Writes ``DIR/results.json`` (``{"coupled": {"axis1": {"A", "B", "C"}, ...}, "per_axis":
{...}, "variants": {...}, "parameters": {...}, ...}``) and ``DIR/torque_B.png`` (measured
and predicted torque per axis on B). Usage: ``python studies/kuka_arm.py --out DIR
[--small]`` (``--small``: without the full and consistent fits).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import jax

TRAJ = ("A", "B", "C")


def _table(err: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """{"axis1": {"A": pct, ...}, ...} from per-trajectory lists of per-axis errors."""
    return {f"axis{j + 1}": {k: float(err[k][j]) for k in err} for j in range(3)}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the study; returns the results (also written to ``results.json``)."""
    jax.config.update("jax_enable_x64", True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxflex.identify.arm import (arm_base, consistent_fit, essential_parameters,
                                   identify_arm, kuka_arm_motion, kuka_counterbalance,
                                   torque_error_pct)
    from jaxflex.data import load_kuka
    from jaxflex.data.kr300 import KR300_GEAR, KR300_JM, kuka_kr300_chain
    from jaxflex.validate import rel_error_pct, rigid_torque, rigid_torque_fit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/kuka_arm")
    ap.add_argument("--small", action="store_true", help="skip the full and consistent fits")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    chain = kuka_kr300_chain()
    mot = {k: kuka_arm_motion(k) for k in TRAJ}
    known = {k: kuka_counterbalance(m) for k, m in mot.items()}

    def errors(fit: Any, motions: dict = mot) -> dict[str, list[float]]:
        return {k: torque_error_pct(m.tau, fit.predict(m, known[k])) for k, m in motions.items()}

    res: dict[str, Any] = {"variants": {}}
    nominal = identify_arm(chain, mot["A"], known["A"], free=())
    err = errors(nominal)
    res["coupled"] = _table(err)
    res["variants"]["nominal"] = {"errors": _table(err), **nominal.to_dict()}
    pred_B = nominal.predict(mot["B"], known["B"])

    held = {k: kuka_arm_motion(k, wrist="held") for k in TRAJ}
    f_held = identify_arm(chain, held["A"], known["A"], free=())
    res["variants"]["nominal_wrist_held"] = {"errors": _table(errors(f_held, held))}
    f_kb = identify_arm(chain, mot["A"], known["A"], free=(), fit_known=True)
    res["variants"]["nominal_fitted_counterbalance"] = {
        "errors": _table(errors(f_kb)), "k_b": f_kb.value("k_b"),
        "k_b_stderr": float(f_kb.stderr[-1])}
    res["rotor_inertia_datasheet"] = {f"Ja{j + 1}": KR300_GEAR[j] ** 2 * KR300_JM[j]
                                      for j in range(3)}

    if not args.small:
        base = arm_base(chain, (0, 1, 2))
        full = identify_arm(chain, mot["A"], known["A"], base=base)
        res["variants"]["full"] = {"errors": _table(errors(full)), **full.to_dict(),
                                   "base_combinations": dict(zip(base.base,
                                                                 base.combinations))}
        ess = essential_parameters(chain, mot["A"], known["A"], base=base)
        f_ess = identify_arm(chain, mot["A"], known["A"], free=ess, base=base)
        res["variants"]["essential"] = {"errors": _table(errors(f_ess)), **f_ess.to_dict()}
        cf = consistent_fit(full, mot["A"], known["A"])
        res["variants"]["consistent"] = {
            "errors": _table({k: torque_error_pct(m.tau, cf.predict(full, m, known[k]))
                              for k, m in mot.items()}),
            "cost": cf.cost, "cost_plain_ls": cf.cost_ls, "chi2_95_threshold": cf.threshold,
            "plain_ls_physical": cf.ls_physical, "converged": cf.converged}

    per_axis: dict[str, dict[str, float]] = {}
    for ax in (1, 2, 3):
        logs = {k: load_kuka(k, ax) for k in TRAJ}
        coef = rigid_torque_fit(logs["A"])
        per_axis[f"axis{ax}"] = {k: rel_error_pct(lg.tau[:, 0], rigid_torque(coef, lg))
                                 for k, lg in logs.items()}
    res["per_axis"] = per_axis
    res["beats_per_axis"] = {a: {k: res["coupled"][a][k] < per_axis[a][k] for k in TRAJ}
                             for a in per_axis}

    fig, axs = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for j in range(3):
        axs[j].plot(mot["B"].t, mot["B"].tau[:, j], lw=0.7, label="measured")
        axs[j].plot(mot["B"].t, pred_B[:, j], lw=0.7, label="coupled arm (fitted on A)")
        axs[j].set_ylabel(f"axis {j + 1}: tau [N m]")
    axs[0].legend(fontsize=7)
    axs[-1].set_xlabel("time [s]")
    axs[0].set_title("KUKA KR300 trajectory B: link-referred motor torque", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "torque_B.png", dpi=110)
    plt.close(fig)

    (out / "results.json").write_text(json.dumps(res, indent=2, default=float) + "\n")
    for name, v in res["variants"].items():
        print(f"{name:32s}", "  ".join(
            f"{a}: " + "/".join(f"{v['errors'][a][k]:.1f}" for k in TRAJ) for a in per_axis))
    print(f"{'per-axis rigid':32s}", "  ".join(
        f"{a}: " + "/".join(f"{per_axis[a][k]:.1f}" for k in TRAJ) for a in per_axis))
    return res


if __name__ == "__main__":
    main()
