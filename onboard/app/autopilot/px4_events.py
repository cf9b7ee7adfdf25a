"""PX4's events (MAVLink EVENT, message 410) in words.

PX4 reports arming refusals, failsafes and its health checks as events, not STATUSTEXT, on the
link a companion uses (measured on v1.16 SITL: its offboard link carried EVENT and no
STATUSTEXT at all; the console said "Arming denied: Resolve system health failures first"), and
pymavlink 2.4.50's dialects do not decode EVENT (it arrives as ``UNKNOWN_410``). An event is an
id and up to 40 bytes of arguments; the words are in the build's event metadata
(``etc/extras/all_events.json.xz`` in a PX4 build: libevents' JSON, per component its event
groups, their message templates with ``{n}`` / ``{n:.dUNIT}`` placeholders for argument n, and its
enums). So ``decode_event`` reads the message's bytes by common.xml's layout, and
``EventMetadata`` (``pmon run --px4-events FILE``) turns one into text; without the file the app
says "refused by PX4 (see its console / events)" where it knows only that arming was refused.

EVENT's wire layout (common.xml; MAVLink 2 orders fields by size and trims trailing zero bytes):
id uint32, event_time_boot_ms uint32, sequence uint16, destination_component uint8,
destination_system uint8, log_levels uint8, arguments uint8[40]. ``id`` is the component id
(bits 24-31: 1 = the autopilot's events) and the event's id within it (bits 0-23). ``log_levels``
bits 0-3: the external log level, which is MAV_SEVERITY's scale (0 emergency .. 7 debug).
Light module (no core import).
"""
from __future__ import annotations

import json
import lzma
import re
import struct
from dataclasses import dataclass
from pathlib import Path

MSG_ID = 410
_LAYOUT = struct.Struct("<IIHBBB40s")
_ARG_TYPES = {"uint8_t": "<B", "int8_t": "<b", "uint16_t": "<H", "int16_t": "<h", "uint32_t": "<I",
              "int32_t": "<i", "uint64_t": "<Q", "int64_t": "<q", "float": "<f"}
_PLACEHOLDER = re.compile(r"\{(\d+)(?::\.(\d+))?([^}]*)\}")
_TAG = re.compile(r"</?[a-z]+[^>]*>")
# groups whose events say why PX4 will not arm (its health and arming checks)
ARMING_GROUPS = ("arming_check", "health")


class EventMetadataError(ValueError):
    """The metadata file cannot be used; the message names it and what is wrong."""


@dataclass(frozen=True)
class Described:
    text: str
    group: str  # its event group: "arming_check" and "health" are PX4's health and arming report
    name: str
    modes: int | None  # its navigation mode group bits (a check: the modes it blocks), if it has them

    @property
    def summary(self) -> bool:
        """The first event of a health / arming report (the checks that fail follow it)."""
        return self.name.endswith("_summary")


@dataclass(frozen=True)
class Event:
    id: int
    time_boot_ms: int
    sequence: int
    log_levels: int
    arguments: bytes

    @property
    def component(self) -> int:
        return self.id >> 24

    @property
    def severity(self) -> int:
        """MAV_SEVERITY (0 emergency .. 7 debug) of its external log level."""
        return min(self.log_levels & 0x0F, 7)


def decode_event(msg) -> Event | None:
    """An EVENT from pymavlink's undecoded message (``UNKNOWN_410``; its raw packet), or None if
    it is not one or is malformed."""
    try:
        buf = bytes(msg.get_msgbuf())
    except Exception:
        return None
    if len(buf) < 12 or buf[0] != 0xFD:  # EVENT exists in MAVLink 2 only
        return None
    length, msg_id = buf[1], int.from_bytes(buf[7:10], "little")
    if msg_id != MSG_ID or length > _LAYOUT.size or len(buf) < 10 + length + 2:
        return None
    payload = buf[10:10 + length].ljust(_LAYOUT.size, b"\0")  # trailing zeros were trimmed
    eid, t, seq, _dcomp, _dsys, levels, args = _LAYOUT.unpack(payload)
    return Event(eid, t, seq, levels, args)


class EventMetadata:
    """A PX4 build's event metadata (libevents JSON, optionally xz-compressed)."""

    def __init__(self, doc: dict, source: str = "?"):
        self.source = source
        self._events: dict[int, tuple[str, dict]] = {}  # full id -> (group, event)
        self._enums: dict[int, dict] = {}
        self._mode_bits: dict[int, int] = {}  # custom_mode -> its navigation mode group's bit
        for cid, comp in (doc.get("components") or {}).items():
            c = int(cid)
            self._enums[c] = comp.get("enums") or {}
            for bit, modes in ((comp.get("navigation_mode_groups") or {}).get("groups") or {}).items():
                for mode in modes:
                    self._mode_bits[int(mode)] = int(bit)
            for group, g in (comp.get("event_groups") or {}).items():
                for sub, ev in (g.get("events") or {}).items():
                    self._events[(c << 24) | int(sub)] = (group, ev)
        if not self._events:
            raise EventMetadataError(f"{source}: no events in it (not PX4 event metadata)")

    @classmethod
    def load(cls, path: str | Path) -> "EventMetadata":
        path = Path(path)
        try:
            raw = path.read_bytes()
            if raw[:6] == b"\xfd7zXZ\x00":
                raw = lzma.decompress(raw)
            doc = json.loads(raw)
        except (OSError, lzma.LZMAError, ValueError) as exc:
            raise EventMetadataError(f"{path}: cannot read PX4 event metadata: {exc}") from None
        if not isinstance(doc, dict):
            raise EventMetadataError(f"{path}: not PX4 event metadata (a JSON object expected)")
        return cls(doc, str(path))

    def __len__(self) -> int:
        return len(self._events)

    def blocks(self, d: Described, custom_mode: int | None) -> bool:
        """A check that blocks the mode ``custom_mode`` (its modes argument has the mode's group;
        a check without one, or a mode the metadata does not group, counts)."""
        bit = self._mode_bits.get(custom_mode) if custom_mode is not None else None
        return d.modes is None or bit is None or bool(d.modes >> bit & 1)

    def describe(self, ev: Event) -> Described | None:
        """An event in words, None if the metadata does not know its id."""
        entry = self._events.get(ev.id)
        if entry is None:
            return None
        group, spec = entry
        specs = spec.get("arguments") or []
        values = self._arguments(ev, specs)
        modes = None
        if specs and str(specs[0].get("type", "")).endswith("navigation_mode_group_t") and len(ev.arguments) >= 4:
            modes = struct.unpack_from("<I", ev.arguments)[0]

        def fill(m: re.Match) -> str:
            i = int(m.group(1)) - 1
            if not 0 <= i < len(values):
                return m.group(0)
            v = values[i]
            if isinstance(v, float) and m.group(2) is not None:
                v = f"{v:.{int(m.group(2))}f}"
            unit = m.group(3).removesuffix("_v")
            return f"{v}{' ' + unit if unit else ''}"
        text = _TAG.sub("", _PLACEHOLDER.sub(fill, str(spec.get("message", ""))))
        return Described(" ".join(text.split()), group, str(spec.get("name", "")), modes)

    def _arguments(self, ev: Event, specs: list) -> list:
        out, at = [], 0
        for a in specs:
            kind = str(a.get("type", ""))
            enum = self._enum(ev.component, kind)
            base = enum.get("type", "") if enum else kind
            fmt = _ARG_TYPES.get(base)
            if fmt is None or at + struct.calcsize(fmt) > len(ev.arguments):
                break
            (v,) = struct.unpack_from(fmt, ev.arguments, at)
            at += struct.calcsize(fmt)
            out.append(self._enum_text(enum, v) if enum else v)
        return out

    def _enum(self, component: int, kind: str) -> dict | None:
        name = kind.removeprefix("px4::")
        for c in (component, 0, 1):
            e = self._enums.get(c, {}).get(name)
            if e:
                return e
        return None

    @staticmethod
    def _enum_text(enum: dict, v: int) -> str:
        entries = enum.get("entries") or {}

        def word(k) -> str:
            e = entries.get(str(k)) or {}
            return str(e.get("description") or e.get("name") or k)
        if enum.get("is_bitfield"):
            return ", ".join(word(1 << b) for b in range(64) if v >> b & 1) or "none"
        return word(v)
