"""Identification of K_t, gravity and friction from current logs (``dragd identify``, docs/IDENTIFICATION.md).

Only names the command line lists live here (importing this package costs nothing): the modules hold the work.
"""

# excitation plans
PLAN_KINDS = ("lowspeed", "symmetric", "friction", "synchronous", "fourier", "gap", "standard", "all")
