"""Figures (host-side, matplotlib). One module per topic; the physics modules never import
this package.

Every ``plot_*`` function builds and returns ``matplotlib.figure.Figure``s made without
pyplot (one, or several by name), so importing this package selects no backend and keeps no
figure alive; whoever wants a file writes it with ``save_figure`` (``save_figures`` for
several by name).
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


def save_figures(figs: dict[str, Figure], folder: str | Path, dpi: int = 110) -> list[str]:
    """Write each figure of ``figs`` as ``folder/<name>.png``.

    **Arguments:**

    - `figs`: file stem -> figure.
    - `folder`: an existing folder.
    - `dpi`: dots per inch.

    **Returns:**

    The file names (without the folder), in the order of ``figs``.
    """
    return [save_figure(fig, Path(folder) / f"{name}.png", dpi) for name, fig in figs.items()]


__all__ = ["new_figure", "save_figure", "save_figures"]
