"""Monte Carlo robustness sweeps: spread files, batched/sharded runs, summaries.

    spec = load_spread("spread.json")          # or parse_spread({...})
    res = run_sweep(spec, samples=10_000, chunk_size=512)
    res.summary["metrics"]["rms_error"]["q95"], res.summary["sensitivity"][0]

See ``spec`` (file format), ``distributions`` (its distributions), ``engine`` (sampling, vmap, chunks, sharding, jax.distributed) and
``summary`` (fixed-size mergeable summaries).
"""

from jaxflex.sweep.engine import (
    build_models,
    nominal_run,
    run_sweep,
    sample_parameters,
    simulate_sample,
)
from jaxflex.sweep.distributions import Distribution, SpreadError, parse_distribution
from jaxflex.sweep.spec import (
    SweepSpec,
    load_spread,
    parse_spread,
    uniform_spread,
)
from jaxflex.sweep.summary import Accumulator, SweepResult, spearman

__all__ = [
    "Accumulator", "Distribution", "SpreadError", "SweepResult", "SweepSpec", "build_models",
    "load_spread", "nominal_run", "parse_distribution", "parse_spread", "run_sweep", "sample_parameters",
    "simulate_sample", "spearman", "uniform_spread",
]
