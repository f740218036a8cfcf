"""Integration on the physics: ``step`` (the one integration step, Strang-split LuGre and RK4,
flexible or rigid model; ``replay`` of a torque sequence) and ``simulate`` (the sampled-data
closed loop and its diffrax reference). Imports only ``jaxflex.core``.
"""
