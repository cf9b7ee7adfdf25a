"""MAVLink 2 message signing for pmon links: one key file, one way to apply it.

Shared by the onboard app (onboard/app/link.py), the mock autopilot (sim/autopilot.py) and the
ground station (``from onboard.app.signing import load_key, apply``; no numpy or core import).

Key file: the 32-byte secret as 64 hexadecimal characters (one line; ``make_key_file`` writes
one). It must be a regular file readable by its owner only (mode 0600 or 0400): a key others
can read is refused, not used. The same key on every system of the vehicle's network; each
link signs with its own link id, and every (sysid, compid, link id) stream must carry
increasing 48-bit timestamps (10 us since 2015-01-01): a replayed packet is rejected.

With signing on, a received packet is accepted only if its signature checks with the key; an
unsigned one only if its message id is in ``ALLOW_UNSIGNED`` (RADIO_STATUS from a radio modem
that cannot sign, as ArduPilot does). pymavlink counts every refusal
(``mav.signing.reject_count``); see ``counts``.
"""
from __future__ import annotations

import os
import stat
import time

ALLOW_UNSIGNED = frozenset({109, 166})  # RADIO_STATUS, RADIO
_EPOCH_2015 = 1420070400


class KeyFileError(ValueError):
    """The key file cannot be used; the message names the file and what is wrong."""


def load_key(path: str | os.PathLike) -> bytes:
    """The 32-byte key from ``path``; KeyFileError if missing, unsafe or malformed."""
    path = os.fspath(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise KeyFileError(f"{path}: cannot read the signing key: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise KeyFileError(f"{path}: the signing key must be a regular file")
    if st.st_mode & 0o077:
        raise KeyFileError(f"{path}: signing key is readable or writable by group/others "
                           f"(mode {stat.S_IMODE(st.st_mode):04o}); chmod 600 {path}")
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        raise KeyFileError(f"{path}: signing key belongs to another user (uid {st.st_uid})")
    with open(path, "rb") as f:
        raw = f.read(200)
    try:
        text = raw.decode("ascii").strip()
        key = bytes.fromhex(text)
    except (UnicodeDecodeError, ValueError):
        key = b""
    if len(key) != 32:
        raise KeyFileError(f"{path}: a signing key is 64 hexadecimal characters (32 bytes)")
    if key == bytes(32):
        raise KeyFileError(f"{path}: an all-zero key disables signing; use a random key")
    return key


def make_key_file(path: str | os.PathLike) -> bytes:
    """Write a new random key to ``path`` (created 0600, never overwritten); returns it."""
    key = os.urandom(32)
    fd = os.open(os.fspath(path), os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    return key


def timestamp_now() -> int:
    """MAVLink signing timestamp: 10 us units since 2015-01-01 UTC."""
    return int((max(time.time(), _EPOCH_2015) - _EPOCH_2015) * 100_000)


def _allow_unsigned(_mav, msg_id: int) -> bool:
    return msg_id in ALLOW_UNSIGNED


def configure(mav, key: bytes, link_id: int, sign_outgoing: bool = True) -> None:
    """Sign and check on a pymavlink ``MAVLink`` protocol object (parser and/or encoder)."""
    if len(key) != 32:
        raise ValueError("a signing key is 32 bytes")
    mav.signing.secret_key = key
    mav.signing.link_id = link_id & 0xFF
    mav.signing.timestamp = max(mav.signing.timestamp, timestamp_now())
    mav.signing.sign_outgoing = sign_outgoing
    mav.signing.allow_unsigned_callback = _allow_unsigned


def apply(conn, key: bytes, link_id: int = 1) -> None:
    """Turn signing on for a ``mavutil.mavlink_connection`` (sign out, check in)."""
    configure(conn.mav, key, link_id)


def counts(mav) -> dict[str, int]:
    """Signing counters of a protocol object: accepted good signatures, bad ones, refused."""
    s = mav.signing
    return {"goodsig": s.goodsig_count, "badsig": s.badsig_count, "unsigned_accepted": s.unsigned_count,
            "rejected": s.reject_count}
