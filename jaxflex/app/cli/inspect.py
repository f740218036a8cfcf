"""``jaxflex inspect FILE``: list a log file's variables (struct fields too) with shapes.

Shows, for a CSV, ``.npz`` or ``.mat`` file, every variable as it is stored, struct fields as
dotted paths (``rec.act_pos_se_deg``), its shape, dtype, the unit where the name tells it
(a log column, or a suffix such as ``_deg``, ``_nm``) and the value of single numbers, so that
a ``--map`` (docs/spec.md section 6.4) can be written without opening MATLAB.

Example:

    jaxflex inspect jaxflex/data/DATA_EMPS.mat
"""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``inspect`` subcommand."""
    p = subparsers.add_parser(
        "inspect", help="list a log file's variables with shapes (to write a --map)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", help="log file (.csv, .npz or .mat)")
    p.add_argument("--json", action="store_true", help="print the list as JSON")
    p.set_defaults(func=run)


def format_table(rows: list[dict]) -> str:
    """The variables as an aligned text table (name, shape, dtype, unit, value)."""
    head = ("variable", "shape", "dtype", "unit", "value")
    body = [(r["name"], "x".join(str(s) for s in r["shape"]) or "scalar", r["dtype"], r["unit"],
             f"{r['value']:.10g}" if "value" in r else "") for r in rows]
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    line = lambda cells: "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()
    return "\n".join([line(head)] + [line(b) for b in body])


def run(args: argparse.Namespace) -> int:
    """Print the variables of ``args.file``; returns the exit code."""
    import json

    from jaxflex.io.logs import inspect_file

    rows = inspect_file(args.file)
    if args.json:
        print(json.dumps(rows, indent=2, default=list))
    else:
        print(format_table(rows))
        print(f"({len(rows)} variables; map them to log columns with --map, "
              "docs/spec.md section 6.4)")
    return 0
