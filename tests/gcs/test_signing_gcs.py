"""MAVLink 2 signing end to end with the real ground station (issue 7, security): `pmon gcs
--signing-key FILE` against a signed SITL stack (mock autopilot + onboard app, every link signed
with one key file) over loopback TCP. A signed GCS's command and parameter write are obeyed; an
unsigned or wrongly signed GCS is refused by the autopilot's link (counted, never routed to the
app) and its CLI says why; an unsafe key file is refused before anything is sent. The key is
read by the one loader, onboard/app/signing.py (app, mock, feed and GCS alike)."""
from __future__ import annotations

import os

import pytest

from sim.stack.sitl_stack import SitlStack

from groundstation.cli import main
from onboard.app import signing
from tests.support.mavlink_gcs import QUICK_BOOT_S

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(90)]


def gcs(capsys, *argv):
    capsys.readouterr()
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.fixture(scope="module")
def signed_stack(tmp_path_factory):
    d = tmp_path_factory.mktemp("signed")
    key_path = d / "pmon.key"
    signing.make_key_file(key_path)
    with SitlStack(speedup=2.0, ready_s=QUICK_BOOT_S, signing_key_path=str(key_path)) as st:
        assert st.ap.wait_until(lambda s: st.app.vehicle.sysid == 1, 20), "signed app must find the signed autopilot"
        assert st.wait_ready()
        yield st, key_path, d


def test_signed_gcs_command_and_parameter_write_are_obeyed(signed_stack, capsys):
    st, key, _ = signed_stack
    rc, out, err = gcs(capsys, "--connect", st.gcs_url, "--signing-key", str(key), "--timeout", "10",
                       "params", "set", "PMON_CLUTTER", "2")
    assert rc == 0, err
    assert st.app.params["PMON_CLUTTER"] == 2.0
    rc, out, err = gcs(capsys, "--connect", st.gcs_url, "--signing-key", str(key), "--timeout", "10", "arm")
    assert rc == 0, err
    assert st.ap.wait_until(lambda s: s.armed, 5), "a signed arm command must arm the vehicle"
    assert st.app.signing_counts()["goodsig"] > 0 and st.app.signing_counts()["badsig"] == 0


def test_unsigned_and_wrongly_signed_gcs_are_rejected_counted_and_told_why(signed_stack, capsys, monkeypatch):
    st, key, d = signed_stack
    monkeypatch.delenv("PMON_GCS_SIGNING_KEY", raising=False)
    before = st.app.params["PMON_CLUTTER"]
    rejected0 = st.ap.counters().get("signing_rejected", 0)
    # unsigned: the GCS hears the (signed) vehicle, but its parameter write never lands
    rc, out, err = gcs(capsys, "--connect", st.gcs_url, "--timeout", "1.5",
                       "params", "set", "PMON_CLUTTER", str(before + 1))
    assert rc == 3, (out, err)
    assert "no answer" in err and "give --signing-key" in err and len(err.strip().splitlines()) == 1
    assert st.app.params["PMON_CLUTTER"] == before
    unsigned = st.ap.counters().get("signing_rejected", 0) - rejected0
    assert unsigned >= 2, st.ap.counters()  # heartbeats and PARAM_SETs, counted by the autopilot
    # wrongly signed (another key): it hears nothing it can verify, and nothing it sends is obeyed
    other = d / "other.key"
    if not other.exists():
        signing.make_key_file(other)
    mode_before = st.ap.state().mode
    rc, out, err = gcs(capsys, "--connect", st.gcs_url, "--signing-key", str(other), "--timeout", "1.5", "rtl")
    assert rc == 3, (out, err)
    assert "failed the signature check" in err
    assert st.ap.state().mode == mode_before
    assert st.ap.counters().get("signing_rejected", 0) - rejected0 > unsigned
    # the app never saw any of it (the autopilot drops what it cannot verify; nothing is routed)
    assert st.app.signing_counts()["badsig"] == 0 and st.app.counters.get("rejected_sysid", 0) == 0


def test_unsafe_or_malformed_key_file_is_refused_before_connecting(tmp_path, capsys):
    wide = tmp_path / "wide.key"
    wide.write_text(os.urandom(32).hex())
    os.chmod(wide, 0o644)
    bad = tmp_path / "short.key"
    bad.write_text("ab" * 8)
    os.chmod(bad, 0o600)
    # nothing listens on this URL: a usage error must come before any connection attempt
    for path, why in ((wide, "chmod 600"), (bad, "64 hexadecimal characters"),
                      (tmp_path / "missing.key", "cannot read")):
        rc, out, err = gcs(capsys, "--connect", "udpin:127.0.0.1:1", "--signing-key", str(path), "status")
        assert rc == 2 and why in err and len(err.strip().splitlines()) == 1, (path, err)
        assert "Traceback" not in err
