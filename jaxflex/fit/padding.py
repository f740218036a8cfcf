"""How a free-start multiple-shooting problem sits in its bucket of segment slots
(``segment_slots``), so that logs of other lengths share one compiled solver, replay and
covariance: ``Padding`` moves unknowns, residual rows and normal blocks between the data's
layout and the slots'.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import numpy as np

from jaxflex.fit.problem import Problem
from jaxflex.fit.segments import segment_slots, slot_rows
from jaxflex.core.validation import to_device


#: The normal-equation and Jacobian blocks of "shooting" that hold one entry per segment.
_SEGMENT_BLOCKS = ("Nxt", "Dx", "U", "gx", "Jt", "Jx", "Jn")


@dataclasses.dataclass(frozen=True)
class Padding:
    """How a free-start multiple-shooting problem of ``count`` segments sits in ``slots``
    (``Problem.padded``): ``my`` output residual rows per segment, ``d`` start entries per
    segment. Moves unknowns, residuals and normal blocks between the two layouts, on the host
    (numpy gathers, one transfer: no device program per shape)."""

    count: int
    slots: int
    my: int
    d: int

    @classmethod
    def of(cls, prob: Problem, *values: Any) -> Padding | None:
        """The padding ``least_squares`` gives ``prob`` (None: it runs as it is): a
        ``Problem`` with free starts and more than two segments (its ``segment_slots``, equal
        to its count or not: every count of a bucket runs the one program), not padded
        already, its arrays and ``values`` concrete (inside a trace a problem runs in its own
        shape: the layouts are moved on the host)."""
        if not (isinstance(prob, Problem) and prob.free_starts and prob.segs.active is None):
            return None
        if any(isinstance(a, jax.core.Tracer)
               for a in jax.tree_util.tree_leaves((eqx.filter(prob, eqx.is_array), values))):
            return None
        S = prob.segs.count
        if S <= 2:  # one and two segments have slots of their own
            return None
        slots = segment_slots(S)
        m = prob.segs.y_meas
        return cls(S, slots, int(m.shape[1] * m.shape[2]), int(np.prod(prob.segs.x0.shape[1:])))

    def unknowns(self, y: Any) -> Any:
        """(theta, x0s) with x0s grown to the slots (copies of the last start)."""
        theta, x0s = y
        return theta, to_device(np.asarray(x0s)[slot_rows(self.count, self.slots)])

    def unknowns_back(self, y: Any) -> Any:
        """(theta, x0s) of the data segments."""
        theta, x0s = y
        return theta, to_device(np.asarray(x0s)[: self.count])

    def rows_back(self, r: Any) -> Any:
        """Residual rows of the data segments: their outputs and their S - 1 defects."""
        r = np.asarray(r)
        out = self.slots * self.my
        return to_device(np.concatenate([r[: self.count * self.my],
                                         r[out: out + (self.count - 1) * self.d]]))

    def rows_in(self, r: Any) -> Any:
        """Residual-shaped rows of the data segments in the slots' layout (zero rows for the
        padding's outputs and for the defects into and between padding slots)."""
        r = np.asarray(r)
        n_out = self.count * self.my
        zeros = lambda k: np.zeros(k, r.dtype)  # noqa: E731
        return to_device(np.concatenate([r[:n_out], zeros((self.slots - self.count) * self.my),
                                         r[n_out:], zeros((self.slots - self.count) * self.d)]))

    def blocks_in(self, normal: dict[str, Any]) -> dict[str, Any]:
        """Normal blocks of the data segments in the slots' layout (zero blocks for the
        padding: a slot no residual sees)."""
        def grow(v):
            v = np.asarray(v)
            return to_device(np.concatenate([v, np.zeros((self.slots - self.count,)
                                                          + v.shape[1:], v.dtype)]))
        return {k: (grow(v) if k in _SEGMENT_BLOCKS else v) for k, v in normal.items()}

    def blocks_back(self, normal: dict[str, Any]) -> dict[str, Any]:
        """The normal blocks of the data segments (per-segment blocks cut to S; a padding
        slot adds nothing to the others: its rows are zero)."""
        return {k: (to_device(np.asarray(v)[: self.count]) if k in _SEGMENT_BLOCKS else v)
                for k, v in normal.items()}
