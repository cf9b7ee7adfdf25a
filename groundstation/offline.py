"""``pmon gcs plot`` and ``pmon gcs export``: a flight from a log file (a tlog or the app's JSONL
run log, with the feed's truth when there is one), no link needed."""
from __future__ import annotations

import math
import os

from groundstation.errors import GcsError, UsageError


def from_log(args, sc) -> tuple[str, dict]:
    """``plot`` or ``export`` (parsed arguments ``args``, the Scenario ``sc``): (text, --json data)."""
    from groundstation.plot import LogError, load
    try:
        flight = load(args.log, args.truth)
    except (LogError, OSError, ValueError) as exc:
        raise GcsError(f"{args.cmd}: {exc}")
    stem = os.path.splitext(args.log)[0]
    what = f"{len(flight.uav)} UAV positions, {len(flight.tracks)} tracks{', with truth' if flight.truth else ''}"
    data = {"uav_points": len(flight.uav), "tracks": len(flight.tracks), "truth": bool(flight.truth)}
    if args.cmd == "plot":
        from groundstation.plot import draw
        out = draw(flight, args.out or stem + ".png", scenario=sc)
        return f"plot: {out} ({what})", {"png": str(out), **data}
    from groundstation.export import parse_times, write
    try:
        at = parse_times(args.at) if args.at else None
    except ValueError as exc:
        raise UsageError(f"export: --at: {exc}")
    if not (math.isfinite(args.every) and args.every >= 0):
        raise UsageError(f"export: --every must be >= 0, got {args.every:g}")
    formats = ("geojson", "kml") if args.format == "both" else (args.format,)
    try:
        paths = write(flight, sc, args.out or stem, formats, at, args.every)
    except OSError as exc:
        raise GcsError(f"export: cannot write: {exc.strerror or exc}")
    return f"export: {', '.join(map(str, paths))} ({what})", {"files": [str(p) for p in paths], **data}
