"""Figures (host-side, matplotlib with the Agg backend). One module per topic; the physics
modules never import this package."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
