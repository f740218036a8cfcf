"""Workflows on the simulated closed loop as a whole: ``analyse`` (its modes by automatic
differentiation: poles at rest, Floquet multipliers along a period) and ``experiments`` (the
paper's experiment section re-run in simulation).
"""
