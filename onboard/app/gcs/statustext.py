"""STATUSTEXT longer than MAVLink's 50 characters, in MAVLink 2 chunks, and their reassembly.

MAVLink 2 (common.xml, STATUSTEXT): ``id`` "may be used to reassemble a logical long-statustext
message from a sequence of chunks; a value of zero indicates this is the only chunk in the
sequence"; ``chunk_seq`` counts the chunks from zero, and "any null character in the text
field is taken to mean this was the last chunk". A text of at most 50 bytes goes as one message
with ``id`` 0, as before; a longer one as 50-byte chunks under one non-zero ``id``, the last
shorter than 50 bytes (an empty chunk follows a text that is an exact multiple of 50 bytes, so
the end is always marked). A ground station that ignores the extension fields still shows each
chunk. ``send_statustext`` is what the app calls; ``Reassembler`` is what the ground station
feeds every STATUSTEXT to.
"""
from __future__ import annotations

import itertools
import threading
import time

CHUNK = 50  # bytes of text in one STATUSTEXT
MAX_CHUNKS = 8  # a text is cut (with "...") past 400 bytes: nothing the app says is longer
_ids = itertools.count(1)
_ids_lock = threading.Lock()


def chunks(text: str) -> list[bytes]:
    """The text as UTF-8 STATUSTEXT payloads: one when it fits, else 50-byte chunks whose
    last one is shorter than 50 (possibly empty). Cut at a character boundary only."""
    raw = text.encode("utf-8", "replace")
    if len(raw) <= CHUNK:
        return [raw]
    limit = CHUNK * MAX_CHUNKS - 1  # the last chunk must stay short of 50 to mark the end
    if len(raw) > limit:
        raw = raw[:limit - 3].decode("utf-8", "ignore").encode() + b"..."
    out, i = [], 0
    while i < len(raw):
        j = min(i + CHUNK, len(raw))
        while j < len(raw) and j > i and (raw[j] & 0xC0) == 0x80:  # never split a character
            j -= 1
        out.append(raw[i:j])
        i = j
    if len(out[-1]) == CHUNK:
        out.append(b"")
    return out


def next_id() -> int:
    """A fresh non-zero 16-bit id for one chunked text (process-wide)."""
    with _ids_lock:
        return (next(_ids) - 1) % 65535 + 1


def send_statustext(link, severity: int, text: str) -> None:
    """Send ``text`` on ``link`` (anything with ``mav`` and ``send``), chunked when needed."""
    parts = chunks(text)
    msg_id = 0 if len(parts) == 1 else next_id()
    for seq, part in enumerate(parts):
        link.send(link.mav.statustext_encode(severity, part, msg_id, seq))


class Reassembler:
    """Whole texts from STATUSTEXT messages: ``feed(msg)`` returns the texts that are complete
    now (usually none or one). A chunked text is returned when its last chunk arrives; one whose
    chunks stop coming is returned after ``timeout_s`` with what arrived, missing chunks marked
    ``[...]`` (a lost chunk never hides the rest). Keyed by sender and id; bounded in size."""

    def __init__(self, timeout_s: float = 2.0, max_pending: int = 32, clock=time.monotonic):
        self.timeout_s = timeout_s
        self.max_pending = max_pending
        self.clock = clock
        self._pending: dict[tuple, dict] = {}  # (sysid, compid, id) -> {"t", "parts", "last"}

    def feed(self, msg) -> list[str]:
        now = self.clock()
        out = self.expire(now)
        text = msg.text if isinstance(msg.text, str) else msg.text.decode("utf-8", "replace")
        msg_id = int(getattr(msg, "id", 0) or 0)
        if msg_id == 0:
            out.append(text)
            return out
        seq = int(getattr(msg, "chunk_seq", 0) or 0)
        key = (msg.get_srcSystem(), msg.get_srcComponent(), msg_id)
        entry = self._pending.get(key)
        if entry is None:
            if len(self._pending) >= self.max_pending:  # a flood of ids: the oldest goes out
                oldest = min(self._pending, key=lambda k: self._pending[k]["t"])
                out.append(self._join(self._pending.pop(oldest)))
            entry = self._pending[key] = {"t": now, "parts": {}, "last": None}
        entry["parts"][seq] = text
        entry["t"] = now
        if len(text.encode("utf-8", "replace")) < CHUNK:  # pymavlink strips the null padding
            entry["last"] = seq
        if entry["last"] is not None and all(k in entry["parts"] for k in range(entry["last"] + 1)):
            out.append(self._join(self._pending.pop(key)))
        return out

    def expire(self, now: float | None = None) -> list[str]:
        """Texts whose chunks stopped coming, with what arrived."""
        now = self.clock() if now is None else now
        late = [k for k, e in self._pending.items() if now - e["t"] > self.timeout_s]
        return [self._join(self._pending.pop(k)) for k in late]

    @staticmethod
    def _join(entry: dict) -> str:
        parts = entry["parts"]
        end = entry["last"] if entry["last"] is not None else max(parts)
        return "".join(parts.get(k, "[...]") for k in range(end + 1)) + ("" if entry["last"] is not None else "[...]")
