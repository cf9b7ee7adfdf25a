"""docs/SETTINGS.md's tables, generated from the declaration (``python -m onboard.settings
--write`` rewrites them; tests/core/test_config.py fails when they drift)."""
from __future__ import annotations

from onboard.settings.declare import default_text, walk
from onboard.settings.sections import Scenario


def markdown_table(experimental: bool = False) -> str:
    """A table of docs/SETTINGS.md, from the declaration: one row per setting that is (or is not)
    experimental; the experimental ones have no PMON_* parameter, so no column for it."""
    rows = (["| key | default | range | meaning |", "|---|---|---|---|"] if experimental else
            ["| key | default | range | in flight | meaning |", "|---|---|---|---|---|"])
    for key, f, s in walk(Scenario):
        if s.experimental != experimental:
            continue
        default = default_text(f) + (" (paper)" if s.paper else "")
        null = "null or " if s.nullable else ""
        flight = "" if experimental else f" {s.param or ''} |"
        rows.append(f"| `{key}` | {default} | {null}{s.range_text()} |{flight} {s.doc.replace('|', chr(92) + '|')} |")
    return "\n".join(rows)


BEGIN, END = "<!-- settings table: begin (python -m onboard.settings --write) -->", "<!-- settings table: end -->"
EXPERIMENTAL_BEGIN = "<!-- experimental settings table: begin (python -m onboard.settings --write) -->"
EXPERIMENTAL_END = "<!-- experimental settings table: end -->"


def docs_with_table(doc: str) -> str:
    """``doc`` with the text between BEGIN and END replaced by ``markdown_table()``, and between
    EXPERIMENTAL_BEGIN and EXPERIMENTAL_END by ``markdown_table(experimental=True)``."""
    for begin, end, experimental in ((BEGIN, END, False), (EXPERIMENTAL_BEGIN, EXPERIMENTAL_END, True)):
        head, sep, rest = doc.partition(begin)
        _, sep2, tail = rest.partition(end)
        if not sep or not sep2:
            raise ValueError(f"no {begin!r} ... {end!r} block")
        doc = f"{head}{begin}\n{markdown_table(experimental)}\n{end}{tail}"
    return doc


def main(argv: list[str] | None = None) -> int:
    import argparse
    from pathlib import Path

    ap = argparse.ArgumentParser(prog="python -m onboard.settings",
                                 description="print the settings tables, or write them into docs/SETTINGS.md")
    ap.add_argument("--write", metavar="FILE", nargs="?", const="docs/SETTINGS.md")
    args = ap.parse_args(argv)
    if args.write is None:
        print(f"{markdown_table()}\n\n{markdown_table(experimental=True)}")
        return 0
    path = Path(args.write)
    path.write_text(docs_with_table(path.read_text(encoding="utf-8")), encoding="utf-8")
    return 0
