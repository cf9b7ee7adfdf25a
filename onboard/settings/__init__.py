"""Every setting of a scenario, declared once: key, default, unit, range and one line of doc.

The declaration is the dataclasses of onboard/settings/sections.py: each field of a section
carries its ``Setting`` (onboard/settings/declare.py) in its metadata (Stone Soup's "each property
declared once with its default and doc"). The declared defaults are what flies (``pmon run``,
``pmon demo``); ``--policy paper`` (onboard/policy.py) is the overlay that restores the paper's
method. Everything else derives from it: the YAML reader and ``--set`` (onboard/config.py), the
policies' overlays (checked as a file is), the PMON_* parameters and their checks
(onboard/app/params.py) and the tables in docs/SETTINGS.md (onboard/settings/docs.py: ``python -m
onboard.settings --write`` regenerates them; a test fails when they drift). A setting declared
``experimental=True`` is a research knob: listed apart, no PMON_* parameter (``Setting``). The
core's parameter classes have no defaults of their own: they take every value from these objects
(their ``from_config``).

This package's entry point is the scenario (``Scenario``) and the error its reader raises
(``ConfigError``); the sections, the machinery and the tables are imported from their modules.
Pure Python (no YAML, no numpy): the ground station imports it for the parameters' ranges.
"""
from onboard.settings.declare import ConfigError
from onboard.settings.sections import Scenario

__all__ = ["ConfigError", "Scenario"]
