"""The 1 Hz tick: its schedule, the worker that runs the core, its log, its overruns and the watchdog over it."""
