"""The base of the top level's results: numbers only, a figure on demand, a JSON file.

A result is a frozen dataclass whose fields hold numbers (floats, numpy arrays, ``Params``,
``CascadeGains``, dicts and lists of them), never a solver's problem or workspace, so that
drawing or saving it runs no JAX.
"""

from __future__ import annotations

import abc
import dataclasses
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxflex.core.controller import CascadeGains
from jaxflex.io.params import Params

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def plain(value: Any) -> Any:
    """``value`` as JSON types: arrays and numpy scalars as lists and numbers, ``Params`` and
    ``CascadeGains`` as their file mappings, non-finite floats as None.

    **Arguments:**

    - `value`: a number, array, ``Params``, ``CascadeGains``, dataclass, mapping or sequence.

    **Returns:**

    The same content in ``dict``, ``list``, ``str``, ``int``, ``float``, ``bool`` and None.
    """
    if isinstance(value, (Params, CascadeGains)):
        return plain(value.to_dict())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray) or hasattr(value, "__array__"):
        return plain(np.asarray(value).tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


class Result(abc.ABC):
    """What every top-level result offers: ``to_json``, ``plot`` and ``save``."""

    def to_json(self) -> dict[str, Any]:
        """Every field as JSON types (``plain``).

        **Returns:**

        A mapping from field name to its JSON value.
        """
        return plain(self)

    @abc.abstractmethod
    def plot(self) -> Figure:
        """The result's figure (matplotlib, made without pyplot; show it in a notebook by
        leaving it last in a cell, or write it with ``jaxflex.app.plots.save_figure``).

        **Returns:**

        A ``matplotlib.figure.Figure``.
        """

    def save(self, path: str | Path, figure: bool = True) -> list[Path]:
        """Write the result as JSON to ``path`` and its figure beside it.

        **Arguments:**

        - `path`: the JSON file (its folder must exist).
        - `figure`: also write ``plot()`` as a PNG with the same name and suffix ``.png``.

        **Returns:**

        The files written.
        """
        from jaxflex.app.plots import save_figure

        path = Path(path)
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")
        written = [path]
        if figure:
            png = path.with_suffix(".png")
            save_figure(self.plot(), png)
            written.append(png)
        return written


def plant_of(model: Any) -> Any:
    """The plant of ``model``: a ``Params`` is built (``Params.to_plant``), a plant is kept.

    **Arguments:**

    - `model`: a ``Params`` or a ``FlexibleJointPlant``.

    **Returns:**

    The ``FlexibleJointPlant``.
    """
    return model.to_plant() if isinstance(model, Params) else model
