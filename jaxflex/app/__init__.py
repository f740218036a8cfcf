"""The edges: ``api`` (the notebook's verbs), ``cli`` (the ``jaxflex`` command), ``plots``
(figures), ``reports`` (report folders) and ``hardware`` (the fixed-period loop around an
exported controller and the simulated rig). The only layer that imports matplotlib or argparse;
nothing below imports it.
"""
