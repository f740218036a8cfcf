"""Logs of measured (or simulated) runs (docs/spec.md section 6): load, validate, save.

A log is a table sampled at a fixed period with columns (SI units, link-referred)

    t [s], tau [N m] applied motor torque, q1 [rad] link angle, q2 [rad] rotor angle,
    optional q1d [rad] reference, F [N m] measured friction, v [rad/s] velocity.

For n joints a column ``c`` is stored as ``c[0]``, ..., ``c[n-1]`` in a CSV header (a single
joint may use the bare name). Formats: CSV with a header row, ``.npz`` and MATLAB ``.mat``
(v5/v7, read with scipy; structs become nested dicts, row vectors are accepted). A
``mapping`` builds each log column from the file's variables (docs/spec.md section 6.4): struct
paths (``rec.time_cont``), selections (``x[0]``, ``x[:,1]``), products and quotients with
numbers or factors from the file (``para.u[0]*rec.act_torque_abs_nm[0]``, ``gtau*vir``) and a
unit suffix converting to SI (``:deg``, ``:ms``); ``@FILE`` reads a map file.
``inspect_file`` lists a file's variables for writing a mapping.

Modules: ``log`` (``Log``), ``readers`` (a file's variables), ``mapping`` (the ``--map``
language), ``files`` (``load_log``, ``inspect_file``, ``save_log``). Everything here is
host-side numpy; a bad log raises ``LogError`` (a ``ValueError``) naming
the problem before any JAX code runs.
"""


from jaxflex.io.logs.log import (
    COLUMN_UNITS,
    LOG_COLUMNS,
    Log,
    LogError,
    REQUIRED_COLUMNS,
)
from jaxflex.io.logs.readers import (
    csv_header,
    gather_indexed,
    read_variables,
)
from jaxflex.io.logs.mapping import (
    MS_SUSPECT_PERIOD,
    UNIT_FACTORS,
    axis_units,
    describe_variables,
    evaluate,
    flatten_variables,
    map_option,
    name_unit,
    parse_mapping,
    split_unit,
)
from jaxflex.io.logs.files import (
    inspect_file,
    load_log,
    save_log,
)

__all__ = [
    "COLUMN_UNITS",
    "LOG_COLUMNS",
    "Log",
    "LogError",
    "MS_SUSPECT_PERIOD",
    "REQUIRED_COLUMNS",
    "UNIT_FACTORS",
    "axis_units",
    "csv_header",
    "describe_variables",
    "evaluate",
    "flatten_variables",
    "gather_indexed",
    "inspect_file",
    "load_log",
    "map_option",
    "name_unit",
    "parse_mapping",
    "read_variables",
    "save_log",
    "split_unit",
]
