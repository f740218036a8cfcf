"""The workflows as a notebook calls them: six verbs, each returning a result of numbers with
``.plot()`` (a matplotlib ``Figure``) and ``.save(path)`` (JSON and the figure).

- ``identify_log(log) -> Identification``: parameters from a log;
- ``discover_effects(log, nominal) -> Discovery``: the named effect a model misses;
- ``validate_model(params, log) -> Validation``: errors on a log beside its noise floors;
- ``certify_gains(params, gains) -> Certification``: the N2 certificate and ultimate bound;
- ``tune_gains(params) -> Tuning``: certified gain tuning;
- ``sweep_spread(spread) -> Sweep``: a Monte Carlo robustness sweep.

Each is a thin layer on the workflow package of the same verb (``jaxflex.identify``,
``jaxflex.discover``, ...), whose engine-level results it turns into numbers. They are
re-exported at the top level (``jaxflex.identify_log``).
"""

from jaxflex.app.api.control import Certification, Tuning, certify_gains, tune_gains
from jaxflex.app.api.discover import Discovery, discover_effects
from jaxflex.app.api.identify import Identification, identify_log
from jaxflex.app.api.result import Result
from jaxflex.app.api.sweep import Sweep, sweep_spread
from jaxflex.app.api.validate import Validation, validate_model

__all__ = [
    "Certification", "Discovery", "Identification", "Result", "Sweep", "Tuning", "Validation",
    "certify_gains", "discover_effects", "identify_log", "sweep_spread", "tune_gains",
    "validate_model",
]
