"""Study: is an effect planted in a real recording named by discrepancy discovery?

Question: take a shipped recording, plant one effect by an exact transformation of its
columns, and run what a user runs on it (``jaxflex.identify_log``, then
``jaxflex.discover_effects`` from the identified parameters, the model kind the
identification used, default settings): is the planted effect named, and is nothing named on
the planted copy that the clean copy does not already have or that the recording cannot
show?

The copies (``COPIES``), each identified and discovered on its own:

- EMPS (``jaxflex:emps/DATA_EMPS``, prismatic, one motor encoder, 1 kHz; its first
  ``EMPS_SECONDS`` s; rigid identification, one substep, at most ``EMPS_IDENTIFY_STEPS``
  steps, taken whether or not it converged, as the notebook verbs take it; the command line
  asks for ``--accept-unconverged`` then):
  clean; a 3 ms delay (the logged force advanced by 3 samples: the axis feels each logged
  force 3 samples late); a constant force offset of 5% of the largest |force| (the logged
  force lowered by it: ``torque_offset``, applied = logged + offset); a link-encoder scale
  (the log's link column read as q1 / (1 + s), s = 0.005, the motor column kept:
  ``encoder_scale``, which the model sees only through the two columns, as two encoders of
  one motion). ``encoder_scale`` is not a default candidate (``candidate = False``), so every
  EMPS copy runs the default candidates and it, the clean copy being the control.
- KUKA KR300 axis 1, trajectory A (``jaxflex:kuka/A/1``, a vertical rotation axis, link and
  motor encoders, 4 ms; rotor-kind identification as the data set's declared coupled link
  side gives it): clean; an 8 ms delay (the logged torque advanced by 2 samples); a torque
  offset of 5% of the largest |torque|; and both planted copies once more, discovered from
  the clean copy's identification (``*_clean_ident``: one identification of the axis, used
  on a later recording of it).

Each copy declares its data set's axis (``NamedData.axis``), as the command line does for a
shipped data set: gravity is not tried on either axis. The transformations hold no random
draw; discovery's gap floor uses its own fixed seed (``gap_floor``'s ``seed = 0``).

Scores per planted copy (``named``): 1 when an effect of the planted family is added alone
in its round, 0.5 when it is added in a tie (``effects_tied``) or is a tied rival of the
effect added, else 0. ``impossible``: effects named that the recording cannot show: a link
encoder reading's effect (``where`` "link encoder reading") on a copy whose two angle
columns are the same samples (one encoder). ``new``: families named on a copy that its
clean copy did not name. ``explained``: the share of the held-out gap's excess over the
floor that the effects added close (``explained_fraction``). ``summary``: the planted copies,
the sum of their scores, the copies that failed, and those with an impossible or new effect.

Writes ``DIR/results.json`` (per copy: what was planted, the identification's convergence
and time, the answer, the effects and ties, the gaps, ``explained``, ``named``,
``impossible``, ``new``, each round's record of the planted family, seconds; a copy that
identification or discovery refuses or fails on gets ``failed`` with the error; the machine's
load average), ``DIR/planted.png``, and each copy's log and identified parameters under
``DIR/<copy>/`` (to rerun ``jaxflex discover`` on them).

Usage: ``python studies/discover_planted.py --out DIR [--copies NAME,...] [--small]``
(``--small``: EMPS's first 3 s, the EMPS clean and delay copies, three candidates).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

#: The EMPS copies' length [s] and their rigid identification's step cap (a user's first
#: look: the full 25 s take minutes to identify).
EMPS_SECONDS = 8.0
EMPS_IDENTIFY_STEPS = 30
#: The size of a planted offset: this share of the recording's largest |tau|.
OFFSET_SHARE = 0.05
#: The planted link-encoder scale error [rad/rad or m/m] (``EncoderScale``'s ``scale``).
SCALE = 0.005


@dataclasses.dataclass(frozen=True)
class Copy:
    """One copy of a recording: the data set (``jaxflex.data.load_named`` spec), what is
    planted (``family``: the effect family that describes it, None for the clean copy) and
    how (``plant``: the log to the planted log), the size in words, extra candidates, and
    whether the clean recording's identification is used instead of the copy's own."""

    name: str
    spec: str
    family: str | None
    plant: Callable[[Any], Any]
    size: str
    extra: tuple[str, ...] = ()
    clean_ident: bool = False


def delayed(samples: int) -> Callable[[Any], Any]:
    """The log with its torque advanced by ``samples``: the joint then receives each logged
    torque ``samples`` periods late (a pure input delay), the last samples dropped."""
    def plant(log):
        n = log.N - samples
        return dataclasses.replace(log.slice(0, n), tau=np.asarray(log.tau)[samples:samples + n])
    return plant


def offset(share: float) -> Callable[[Any], Any]:
    """The log with its torque lowered by ``share`` of its largest |tau|: the joint receives
    the logged torque plus that constant (``torque_offset``)."""
    def plant(log):
        tau = np.asarray(log.tau, float)
        return dataclasses.replace(log, tau=tau - share * float(np.max(np.abs(tau))))
    return plant


def scaled_link(scale: float) -> Callable[[Any], Any]:
    """The log with its link column read as q1 / (1 + ``scale``) (``encoder_scale``), the
    motor column kept."""
    def plant(log):
        return dataclasses.replace(log, q1=np.asarray(log.q1, float) / (1.0 + scale))
    return plant


def clean(log):
    """The recording as shipped."""
    return log


EMPS, KUKA = "jaxflex:emps/DATA_EMPS", "jaxflex:kuka/A/1"
COPIES: tuple[Copy, ...] = (
    Copy("emps_clean", EMPS, None, clean, "-", ("encoder_scale",)),
    Copy("emps_delay", EMPS, "time_delay", delayed(3), "3 ms (3 samples)", ("encoder_scale",)),
    Copy("emps_offset", EMPS, "torque_offset", offset(OFFSET_SHARE),
         f"{OFFSET_SHARE:.0%} of max |force|", ("encoder_scale",)),
    Copy("emps_scale", EMPS, "encoder_scale", scaled_link(SCALE), f"s = {SCALE}",
         ("encoder_scale",)),
    Copy("kuka1_clean", KUKA, None, clean, "-"),
    Copy("kuka1_delay", KUKA, "time_delay", delayed(2), "8 ms (2 samples)"),
    Copy("kuka1_offset", KUKA, "torque_offset", offset(OFFSET_SHARE),
         f"{OFFSET_SHARE:.0%} of max |torque|"),
    Copy("kuka1_delay_clean_ident", KUKA, "time_delay", delayed(2), "8 ms (2 samples)",
         clean_ident=True),
    Copy("kuka1_offset_clean_ident", KUKA, "torque_offset", offset(OFFSET_SHARE),
         f"{OFFSET_SHARE:.0%} of max |torque|", clean_ident=True),
)
#: ``--small``: the copies and candidates of the slow test's run.
SMALL_COPIES = ("emps_clean", "emps_delay")
SMALL_CANDIDATES = ("time_delay", "torque_offset", "asymmetric_friction")


def recording(spec: str, small: bool) -> tuple[Any, list[str], list[str]]:
    """The shipped recording ``spec`` (EMPS cut to its first ``EMPS_SECONDS`` s, 3 s with
    ``small``), its declared axis kinds and link sides."""
    from jaxflex.data import load_named

    nd = load_named(spec)
    log = nd.log
    if spec == EMPS:
        log = log.slice(0, int(round((3.0 if small else EMPS_SECONDS) / log.dt)))
    return log, list(nd.axis or []), list(nd.link_side or [])


def run_copy(copy: Copy, small: bool, out: Path) -> dict[str, Any]:
    """Identify and discover one copy as a user would; its record (module docstring). The
    planted log and its identified parameters are written under ``out / copy.name``."""
    import jaxflex
    from jaxflex.discover import model_kind_of
    from jaxflex.io.logs import save_log
    from jaxflex.io.params import save_params

    log, axis, side = recording(copy.spec, small)
    planted = copy.plant(log)
    t0 = time.perf_counter()
    identified = log if copy.clean_ident else planted
    if copy.spec == EMPS:
        ident = jaxflex.identify_log(identified, model="rigid", substeps=1,
                                     max_steps=EMPS_IDENTIFY_STEPS)
    else:
        ident = jaxflex.identify_log(identified, model="auto", link_side=side)
    t_ident = time.perf_counter() - t0
    params = ident.params
    if axis:
        params.extra["axis"] = axis[0]
    folder = out / copy.name
    folder.mkdir(parents=True, exist_ok=True)
    save_log(planted, folder / "log.csv")
    save_params(params, folder / "params.json")
    kind = model_kind_of(params) or "flexible"
    config: dict[str, Any] = {"model": kind}
    if small:
        config["candidates"] = SMALL_CANDIDATES
    elif copy.extra:
        from jaxflex.core.effects import candidate_effects
        from jaxflex.discover import cannot_act

        ruled_out = cannot_act(params)
        config["candidates"] = [c for c in candidate_effects() if c not in ruled_out] + list(
            copy.extra)
    t0 = time.perf_counter()
    found = jaxflex.discover_effects(planted, params, **config)
    rep = found.report
    one_encoder = bool(np.array_equal(np.asarray(planted.q1), np.asarray(planted.q2)))
    return {
        "spec": copy.spec, "planted": copy.family, "size": copy.size,
        "identified": "clean copy" if copy.clean_ident else "this copy",
        "samples": int(planted.N), "dt": float(planted.dt), "model": kind,
        "identification": {"converged": ident.converged, "verdict": ident.verdict,
                           "effects": sorted(params.effects), "seconds": t_ident},
        "candidates": rep["config"]["candidates"],
        "answer": found.answer, "effect": rep["effect"], "effects": rep["effects"],
        "families": rep["families"], "effects_tied": rep["effects_tied"],
        "gap_before": found.gap_before, "gap_after": found.gap_after,
        "gap_floor": found.gap_floor, "explained": found.explained,
        "named": named_score(rep, copy.family) if copy.family else None,
        "impossible": impossible(rep, one_encoder),
        "rounds": screens(rep, copy.family) if copy.family else None,
        "seconds": time.perf_counter() - t0,
    }


def named_score(rep: dict[str, Any], family: str) -> float:
    """1 when an effect of ``family`` was added alone in its round, 0.5 when in a tie, else
    0 (module docstring)."""
    from jaxflex.core.effects import EFFECTS

    best = 0.0
    for tie in rep["effects_tied"]:
        fams = [EFFECTS[n].family_name() if n in EFFECTS else n.split(" order ")[0]
                for n in tie]
        if family in fams:
            best = max(best, 1.0 if len(tie) == 1 else 0.5)
    return best


def impossible(rep: dict[str, Any], one_encoder: bool) -> list[str]:
    """The effects named that the recording cannot show (module docstring)."""
    from jaxflex.core.effects import EFFECTS

    if not one_encoder:
        return []
    return [n for n in rep["effects"] if EFFECTS[n].where == "link encoder reading"]


def screens(rep: dict[str, Any], family: str) -> list[dict[str, Any] | None]:
    """Each round's record of the planted family's candidate (None where the round did not
    try it): screened out or fitted, its F-test p-value, dAIC, held-out gain, significance,
    the screen's predicted p-value and dAIC and the fitted parameters."""
    out = []
    for r in rep["rounds"]:
        s = r["scores"].get(family)
        if s is None:
            out.append(None)
            continue
        keys = ("screened_out", "p_value", "dAIC", "dBIC", "gain", "significant")
        rec = {k: s.get(k) for k in keys}
        scr = s.get("screen") or {}
        rec |= {k: scr.get(k) for k in ("predicted_p_value", "predicted_dAIC", "params")
                if k in scr}
        rec["fitted"] = r.get("fitted", {}).get(family)
        out.append(rec)
    return out


def plot(results: dict[str, Any], path: Path) -> None:
    """The held-out gap before and after each copy's effects, over its floor, the planted
    copies marked by their score (no figure when every copy failed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [k for k, r in results["copies"].items() if "failed" not in r]
    if not names:  # every copy failed: their errors are in results.json
        return
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 3, 5))
    x = np.arange(len(names))
    r = [results["copies"][n] for n in names]
    ax.bar(x - 0.2, [c["gap_before"] for c in r], 0.4, label="nominal refit")
    ax.bar(x + 0.2, [c["gap_after"] for c in r], 0.4, label="with the effects named")
    ax.scatter(x, [c["gap_floor"] for c in r], color="k", marker="_", s=400, label="floor",
               zorder=3)
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{n}\n{textwrap.fill(c['answer'], 22)}\nnamed {c['named']}"
                      for n, c in zip(names, r)], fontsize=7)
    ax.set_ylabel("held-out gap")
    ax.set_title("Planted effects on real recordings: are they named?")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the copies; write results.json and planted.png; returns the results."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/discover_planted")
    ap.add_argument("--copies", default=None,
                    help=f"comma-separated names of {[c.name for c in COPIES]} (default all)")
    ap.add_argument("--small", action="store_true",
                    help="EMPS's first 3 s, the clean and delay copies, three candidates")
    a = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    chosen = (a.copies.split(",") if a.copies else
              list(SMALL_COPIES) if a.small else [c.name for c in COPIES])
    by_name = {c.name: c for c in COPIES}
    unknown = sorted(set(chosen) - set(by_name))
    if unknown:
        raise SystemExit(f"unknown copies {unknown}; known: {sorted(by_name)}")
    results: dict[str, Any] = {"question": __doc__.splitlines()[0], "small": a.small,
                               "emps_seconds": 3.0 if a.small else EMPS_SECONDS,
                               "load_avg_start": list(os.getloadavg()),
                               "cpu_count": os.cpu_count(), "copies": {}}
    for name in chosen:
        try:
            rec = run_copy(by_name[name], a.small, out)
        except (ValueError, RuntimeError) as e:  # refused or a solver failure: recorded
            results["copies"][name] = {"spec": by_name[name].spec,
                                       "planted": by_name[name].family, "failed": repr(e)}
            print(f"{name:14s} failed: {e}", flush=True)
            continue
        results["copies"][name] = rec
        (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
        print(f"{name:14s} planted {str(rec['planted']):14s} answer {rec['answer']!r} "
              f"named {rec['named']} explained {rec['explained']:.2f} gap "
              f"{rec['gap_before']:.4g} -> {rec['gap_after']:.4g} (floor "
              f"{rec['gap_floor']:.2g}) {rec['seconds']:.0f} s", flush=True)
    done = {k: r for k, r in results["copies"].items() if "failed" not in r}
    for rec in done.values():  # what the clean copy of its data set named
        base = next((r for r in done.values()
                     if r["spec"] == rec["spec"] and r["planted"] is None), None)
        if base is not None:
            rec["new"] = sorted(set(rec["families"]) - set(base["families"])
                                - {rec["planted"]})
    scores = [r["named"] for r in done.values() if r["planted"] is not None]
    results["summary"] = {
        "planted": sum(1 for r in results["copies"].values() if r["planted"] is not None),
        "named": sum(scores), "failed": sorted(k for k, r in results["copies"].items()
                                               if "failed" in r),
        "impossible": {k: r["impossible"] for k, r in done.items() if r["impossible"]},
        "new": {k: r["new"] for k, r in done.items() if r.get("new")}}
    results["load_avg_end"] = list(os.getloadavg())
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    plot(results, out / "planted.png")
    return results


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
