"""The physics: the paper's equations as pure functions and ``eqx.Module``s, and nothing else.

``friction`` (LuGre, eq. 4-7, 35), ``effects`` (the named effects a plant is composed of),
``plant`` (eq. 3, 8, 40), ``chain`` and ``inertial`` (a serial arm's rigid-body dynamics),
``observer`` (eq. 18-22), ``estimator`` (Kalman velocity estimation), ``sensing``,
``controller`` (eq. 9-16), ``trajectory``, ``certificate`` (eq. 24-33); ``state`` and
``validation`` (shape and value checks) are what they share. Every other layer uses these; they
import nothing from the rest of jaxflex (``docs/architecture.md``).
"""
