"""The onboard app: the imperative shell (MAVLink, DF datagrams, clock, state machine, logs)
around the functional core ``onboard.core``. Entry point: ``pmon run``."""
