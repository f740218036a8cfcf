"""Figures (host-side, matplotlib). One module per topic; the physics modules never import
this package.

Every ``plot_*`` function builds and returns a ``matplotlib.figure.Figure`` made without
pyplot, so importing this package selects no backend and keeps no figure alive; whoever wants
a file writes it with ``save_figure``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.figure import Figure


def new_figure(*grid: int, figsize: tuple[float, float], **kwargs: Any) -> tuple[Figure, Any]:
    """A figure and its axes, as ``pyplot.subplots`` gives them, without pyplot.

    **Arguments:**

    - `grid`: rows and columns of axes (none: one axes).
    - `figsize`: (width, height) [inch].
    - `kwargs`: passed to ``Figure.subplots`` (``sharex``, ``squeeze``, ...).

    **Returns:**

    ``(figure, axes)``: one ``Axes`` or an array of them, as ``Figure.subplots`` gives.
    """
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*grid, **kwargs)


def save_figure(fig: Figure, path: str | Path, dpi: int = 110) -> str:
    """Write ``fig`` as a PNG to ``path``.

    **Arguments:**

    - `fig`: the figure.
    - `path`: the file to write.
    - `dpi`: dots per inch.

    **Returns:**

    The file's name (without its folder).
    """
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    return path.name


__all__ = ["new_figure", "save_figure"]
