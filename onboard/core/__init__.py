"""The functional core: pure numpy/scipy maths.

No sockets, clocks (timers are injected), threads, logging side effects or global RNG state here;
every random function takes a ``numpy.random.Generator``. SI units and radians throughout;
positions are in the ENU mission frame (x east, y north, z up), metres.
"""
