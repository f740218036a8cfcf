"""Compile-time machinery, under everything else and behind a small interface: ``tracecache``
(traced programs kept across processes, ``persistent_jit``), ``ahead`` (compilation in a
background thread, independent work side by side) and ``xla`` (XLA options set before JAX
starts). A speed switch, never a physics argument: ``jaxflex.core`` and ``jaxflex.sim`` import
nothing from here.
"""
