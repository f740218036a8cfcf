"""What comes in from files and names: ``logs`` (the one ``Log`` type and its readers and
writers), ``params`` (parameter files and the one Params -> plant builder), ``presets`` (the
paper's tables and every named preset) and ``errors`` (the kinds of failure a caller is told).
Imports only ``jaxflex.core``.
"""
