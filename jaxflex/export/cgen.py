"""Write the controller as C99 (a source and a header) from the same traced programs as the
Python export (``jaxflex.export.tracing.trace``), translated with the C dialect
(``jaxflex.export.dialect.C99``).

The controller's constants are folded into the code (the C export has no parameter
overrides: export again for other values). Every value is a double; the state is a fixed
array of doubles (``jaxflex_state_size`` bytes) that the caller owns. No dependency beyond
libm. Compile without value-changing optimisations (no ``-ffast-math``) and with
``-ffp-contract=off``, so that every multiply and add is rounded as the traced program
rounds it.
"""

from __future__ import annotations

import datetime
import json
import re
import textwrap


from jaxflex.export.atoms import Program, Sym, const_array, eliminate_dead
from jaxflex.export.dialect import C99, format_atom
from jaxflex.export.program import REFERENCE_ROWS, describe
from jaxflex.export.tracing import (
    SPEC_ENTRIES,
    Traced,
    listed_leaves,
    trace,
    translate_program,
)

C_FLAGS: tuple[str, ...] = ("-std=c99", "-O2", "-ffp-contract=off", "-fno-fast-math")
"""Compiler flags the generated C is checked with (gcc/clang syntax)."""

_C_FUNCS = ("init", "step", "init_ref", "step_ref", "reference", "reference_derivatives")


def _body(prog: Program, outputs: list[str]) -> list[str]:
    """The statements of ``prog`` that its outputs need, then ``outputs[i] = value``."""
    live = {a.name for a in prog.outputs if isinstance(a, Sym)}
    dyn = eliminate_dead(prog.dyn_stmts, live)
    stat = eliminate_dead(prog.static_stmts, live)
    lines = []
    for st in [*stat, *dyn]:
        if len(st.targets) == 1:
            lines.append(f"const double {st.targets[0]} = {st.code};")
        else:
            lines.append(f"double {', '.join(st.targets)};")
            lines.append(f"{st.code};")
    for dst, a in zip(outputs, prog.outputs):
        lines.append(f"{dst} = {format_atom(a, C99)};")
    return lines


def _unpack(sig_names: list[tuple[str, str, int]]) -> list[str]:
    """``const double name_k = array[k];`` for each (symbol prefix, C array, size)."""
    return [f"const double {sym}_{k} = {arr}[{k}];"
            for sym, arr, size in sig_names for k in range(size)]


def generate_c(controller: object = None, *, traced: Traced | None = None,
               header_name: str = "controller.h", description: str = "") -> tuple[str, str]:
    """C99 source and header of the controller.

    **Arguments:**

    - ``controller``: a ``SampledController`` or ``CascadeController`` (ignored when
      ``traced`` is given).
    - ``traced``: the programs traced by ``jaxflex.export.tracing.trace``.
    - ``header_name``: the header's file name, as the source includes it.
    - ``description``: the first line of both files' comment.

    **Returns:**

    ``(source, header)``. The header declares ``jaxflex_state_size``, ``jaxflex_reset``,
    ``jaxflex_step`` (recorded reference), ``jaxflex_step_ref`` (the rig's reference:
    q1d and its first four derivatives, ``JAXFLEX_REF_ROWS`` x n row-major),
    ``jaxflex_reference``, ``jaxflex_reference_derivatives`` and ``jaxflex_info`` (JSON).

    **Raises:**

    ``UnsupportedPrimitive`` naming a primitive it cannot translate; ``ExportError`` for a
    configuration the export cannot run.
    """
    import jax

    tr = trace(controller) if traced is None else traced
    with jax.enable_x64(True):
        params = [const_array(v) for v in tr.values]
        progs = {name: translate_program(tr, name, params, C99) for name in _C_FUNCS}
        listed = listed_leaves(tr)
    n, ns, rows = tr.n, tr.n_state, REFERENCE_ROWS
    c = tr.sc.controller
    desc = description or "Cascade controller with LuGre friction observer"
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    # state symbols s{i}_{k} sit at offset sum(sizes[:i]) + k of the state array
    state_unpack, off = [], 0
    for i, size in enumerate(tr.state_sizes):
        state_unpack += [f"const double s{i}_{k} = s[{off + k}];" for k in range(size)]
        off += size
    q_unpack = _unpack([("q1", "q1", n), ("q2", "q2", n)])
    r_unpack = _unpack([("r", "ref", rows * n)])

    def fn(name: str, sig: str, unpack: list[str], outs: list[str]) -> str:
        body = _body(progs[name], outs)
        text = "\n".join(body)
        # only the inputs the code reads (a compiler warns about the others)
        unpack = [u for u in unpack if re.search(rf"\b{u.split()[2]}\b", text)]
        body = unpack + body
        return f"static void jf_{name}({sig})\n{{\n" + "".join(f"    {b}\n" for b in body) + "}\n"

    new_state = [f"out[{k}]" for k in range(ns)]
    tau = [f"tau[{k}]" for k in range(n)]
    funcs = [
        fn("init", "double t, const double *q1, const double *q2, double *out",
           q_unpack, new_state),
        fn("init_ref", "double t, const double *q1, const double *q2, const double *ref, "
           "double *out", q_unpack + r_unpack, new_state),
        fn("step", "const double *s, double t, const double *q1, const double *q2, "
           "double *out, double *tau", state_unpack + q_unpack, new_state + tau),
        fn("step_ref", "const double *s, double t, const double *q1, const double *q2, "
           "const double *ref, double *out, double *tau",
           state_unpack + q_unpack + r_unpack, new_state + tau),
        fn("reference", "double t, double *q1d", [], [f"q1d[{k}]" for k in range(n)]),
        fn("reference_derivatives", "double t, double *ref", [],
           [f"ref[{k}]" for k in range(rows * n)]),
    ]
    info = {
        "n_joints": n, "dt": float(c.dt), "q2d_method": c.q2d_method,
        "velocity": tr.sc.sensing.velocity, "config": describe(tr.sc),
        "reference_rows": rows, "state_names": tr.state_names,
        "params": {tr.names[i]: [list(tr.values[i].shape), tr.values[i].reshape(-1).tolist()]
                   for i in listed},
        "spec_map": {k: v for k, v in SPEC_ENTRIES.items()
                     if v in {tr.names[i] for i in listed}},
    }
    info_c = json.dumps(json.dumps(info, separators=(",", ":")))  # a C string literal
    guard = "JAXFLEX_CONTROLLER_H"
    src_name = header_name.removesuffix(".h") + ".c"
    text = (f"{desc} -- C99 export.\n\nGenerated by jaxflex export on {date} from the traced "
            "JAX definition (jaxflex.export.SampledController.init / .step); DO NOT EDIT: "
            "change the JAX controller and export again. Needs only libm.\n\n"
            f"Joints: {n}; sample period dt = {float(c.dt)!r} s; q2d_method = {c.q2d_method}; "
            f"friction compensation: {c.compensation}; controller-side sensing: "
            f"{describe(tr.sc)}.\n\nState (doubles): [0] started flag, then "
            + ", ".join(f"[{1 + i}] {nm}" for i, nm in enumerate(_state_labels(tr)))
            + f".\n\nCompile with: cc {' '.join(C_FLAGS)} -c {src_name} (link with -lm).")
    lines = [line for par in text.split("\n") for line in (textwrap.wrap(par, 88) or [""])]
    comment = "/* " + "\n".join((" * " + x).rstrip() for x in lines)[3:] + "\n */\n"
    header = comment + f"""#ifndef {guard}
#define {guard}

#ifdef __cplusplus
extern "C" {{
#endif

#define JAXFLEX_N_JOINTS {n}
#define JAXFLEX_DT {float(c.dt)!r}
#define JAXFLEX_STATE_DOUBLES {ns + 1}
#define JAXFLEX_REF_ROWS {rows}

/* Bytes of controller state the caller provides (JAXFLEX_STATE_DOUBLES doubles). */
int jaxflex_state_size(void);
/* Forget the state; the next step starts the filters and the observer from its angles. */
void jaxflex_reset(void *state);
/* One sample at time t [s]: link and rotor angles q1, q2 [rad] (n each) -> motor torque
   tau [N m] (n), the command before the DAC, with the recorded reference. Call once per dt. */
void jaxflex_step(void *state, double t, const double *q1, const double *q2, double *tau);
/* As jaxflex_step with the rig's reference at t: ref is JAXFLEX_REF_ROWS x n row-major,
   rows q1d [rad], q1d' [rad/s], q1d'', q1d^(3), q1d^(4). */
void jaxflex_step_ref(void *state, double t, const double *q1, const double *q2,
                      const double *ref, double *tau);
/* The recorded reference q1d(t) [rad] (n). */
void jaxflex_reference(double t, double *q1d);
/* The recorded reference at t as jaxflex_step_ref takes it (JAXFLEX_REF_ROWS x n). */
void jaxflex_reference_derivatives(double t, double *ref);
/* JSON: joints, dt, q2d method, velocity source, state names, constants. */
const char *jaxflex_info(void);

#ifdef __cplusplus
}}
#endif

#endif
"""
    code = "\n".join(funcs)
    helpers = []
    if "jf_sign(" in code:
        helpers.append(_SIGN)
    source = comment + f"""#include <math.h>
#include "{header_name}"

#define NS {ns}

{"".join(helpers)}{code}

int jaxflex_state_size(void)
{{
    return (int)sizeof(double) * (NS + 1);
}}

void jaxflex_reset(void *state)
{{
    ((double *)state)[0] = 0.0;
}}

void jaxflex_step(void *state, double t, const double *q1, const double *q2, double *tau)
{{
    double *st = (double *)state, next[NS > 0 ? NS : 1];
    int i;
    if (st[0] == 0.0) {{
        jf_init(t, q1, q2, st + 1);
        st[0] = 1.0;
    }}
    jf_step(st + 1, t, q1, q2, next, tau);
    for (i = 0; i < NS; i++) st[1 + i] = next[i];
}}

void jaxflex_step_ref(void *state, double t, const double *q1, const double *q2,
                      const double *ref, double *tau)
{{
    double *st = (double *)state, next[NS > 0 ? NS : 1];
    int i;
    if (st[0] == 0.0) {{
        jf_init_ref(t, q1, q2, ref, st + 1);
        st[0] = 1.0;
    }}
    jf_step_ref(st + 1, t, q1, q2, ref, next, tau);
    for (i = 0; i < NS; i++) st[1 + i] = next[i];
}}

void jaxflex_reference(double t, double *q1d)
{{
    jf_reference(t, q1d);
}}

void jaxflex_reference_derivatives(double t, double *ref)
{{
    jf_reference_derivatives(t, ref);
}}

const char *jaxflex_info(void)
{{
    return {info_c};
}}
"""
    return source, header



_SIGN = """static double jf_sign(double x)
{
    return x > 0 ? 1.0 : (x < 0 ? -1.0 : x);
}

"""


def _state_labels(tr: Traced) -> list[str]:
    """The state's values by name, one per joint (``z_hat[0]``, ...)."""
    return [f"{nm}[{k}]" if size > 1 else nm
            for nm, size in zip(tr.state_names, tr.state_sizes) for k in range(size)]
