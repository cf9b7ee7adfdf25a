"""The KrakenSDR reader against a hostile HTTP server in its place (issue 45, items 1-4 and 10):
each server here is on 127.0.0.1, scripted byte by byte (tests/support/kraken_rig.py), and
stops by itself. The reader must refuse what is not HTTP with a counted error, keep its
deadline whatever the peer sends, never die, and cost one request per read."""
from __future__ import annotations

import time

import pytest
import yaml

from onboard.app.kraken import line as kl
from onboard.app.autopilot.clock import ManualClock
from onboard.app.kraken.fetch import DocumentPoller, FetchError, HttpSource
from onboard.cli import main
from onboard.config import ConfigError, override
from tests.support.app_helpers import wait_for
from tests.support.kraken_rig import SC, HostileServer, M, frame, http_answer, kraken_app

pytestmark = pytest.mark.timeout(60)
DOC = frame(10.0, [[0.1]] * M, 0).encode()


def _serve(served: list[bytes], keep_alive: bool = True):
    """Answer every request with ``served[0]`` as it is then (``keep_alive`` False: then close,
    without saying so)."""
    def script(n, conn):
        conn.sendall(http_answer(served[0]))
        return keep_alive
    return script


# ----------------------------------------------------------------------------- item 1
# b"\xb2" is read (ISO-8859-1, as http.client reads headers) as "²", a digit to str.isdigit() but
# not to int(); the others are no number either
BAD_LENGTHS = (b"\xb2", b"\xb9\xb2", "١٢".encode(), b"5, 5", b"-3", b"0x10", b"12a")


def test_a_content_length_that_is_no_ascii_number_is_refused_and_the_reader_goes_on():
    def script(n, conn):
        if n < len(BAD_LENGTHS):
            conn.sendall(http_answer(DOC, length=BAD_LENGTHS[n], keep_alive=False))
            return False
        conn.sendall(http_answer(DOC))
        return True

    with HostileServer(script) as srv:
        poller = DocumentPoller(srv.url, None, 0.01, timeout_s=0.5).start()
        try:
            assert wait_for(lambda: poller.documents == 1, 10), (poller.errors, poller.reads)
            assert poller._thread.is_alive()
        finally:
            poller.stop()
    assert poller.errors == {"doa bad_http": len(BAD_LENGTHS)}, poller.errors
    assert "Content-Length" in poller.last_error["doa"] and poller.restarts == 0
    assert [d for _, d, _ in poller.queue] == [DOC]  # the genuine answer, whole


# ----------------------------------------------------------------------------- item 2
def test_a_url_that_is_not_ascii_is_refused_before_any_read(tmp_path, capsys):
    with HostileServer(_serve([DOC])) as srv:
        base = f"http://127.0.0.1:{srv.port}"
        for key, url, c, code in (("kraken.url", base + "/café/DOA_value.html", "é", "%C3%A9"),
                                  ("kraken.status_url", base + "/status.json?v=²", "²", "%C2%B2")):
            with pytest.raises(ConfigError) as e:
                override(SC, {key: url})
            assert str(e.value).startswith(f"{key}: must be ASCII: percent-encode its path and query "
                                           f"({c!r}, character {url.index(c) + 1}, is {code}), got ")
        with pytest.raises(ConfigError, match=r"kraken.url: its host must be ASCII"):
            override(SC, {"kraken.url": "http://kräken:8081/DOA_value.html"})
        # the same refusals from the command line, one line each, before anything starts
        tree = yaml.safe_load(open("config/paper.yaml"))
        tree["kraken"]["url"] = base + "/café/DOA_value.html"
        path = tmp_path / "cafe.yaml"
        path.write_text(yaml.safe_dump(tree, allow_unicode=True), encoding="utf-8")
        capsys.readouterr()
        for argv in (["check-config", str(path)],
                     ["run", "--mavlink", "udpin:127.0.0.1:0", "--df", "127.0.0.1:0", "--kraken",
                      base + "/café/DOA_value.html"]):
            rc = main(argv)
            err = capsys.readouterr().err.strip()
            assert rc == 2 and "\n" not in err and "kraken.url: must be ASCII" in err, (argv[0], rc, err)
        with pytest.raises(ValueError, match="not ASCII"):
            HttpSource(base + "/café", kl.MAX_DOC_BYTES)
        assert srv.requests == 0  # nothing was sent for any of them
        # written as the message says: read, and the server is asked for that path
        assert HttpSource(base + "/caf%C3%A9/DOA_value.html", kl.MAX_DOC_BYTES, 0.5).get() == DOC
        assert srv.paths == ["/caf%C3%A9/DOA_value.html"]


# ----------------------------------------------------------------------------- item 3
def _trickle(data: bytes, gap_s: float = 0.05, piece: int = 1, at_once: int = 0):
    """An answer sent ``piece`` bytes every ``gap_s`` (each far within a per-receive timeout),
    its first ``at_once`` bytes at once."""
    def script(n, conn):
        conn.sendall(data[:at_once])
        for i in range(at_once, len(data), piece):
            conn.sendall(data[i:i + piece])  # OSError once the reader hung up: the server stops
            time.sleep(gap_s)
        return False
    return script


STALLS = {
    "status line trickled": _trickle(b"HTTP/1.1 200 OK" + b" " * 100 + b"\r\n"),
    "headers trickled": _trickle(b"HTTP/1.1 200 OK\r\n" + b"".join(b"X-%d: a\r\n" % i for i in range(95)),
                                 piece=8),
    "100 Continue, again and again": _trickle(b"HTTP/1.1 100 Continue\r\n\r\n" * 100, piece=25),
    "body trickled": _trickle(http_answer(b"x" * 100), at_once=len(http_answer(b"x" * 100)) - 100),
}


@pytest.mark.parametrize("how", list(STALLS))
def test_no_peer_holds_a_read_beyond_its_deadline(how):
    timeout_s = 0.5
    with HostileServer(STALLS[how]) as srv:
        src = HttpSource(srv.url, kl.MAX_DOC_BYTES, timeout_s=timeout_s)
        t0 = time.monotonic()
        with pytest.raises(FetchError) as e:
            src.get()
        took = time.monotonic() - t0
        src.close()
    assert e.value.kind == "timeout", e.value
    assert timeout_s - 0.05 < took < timeout_s + 0.25, took  # the trickle alone lasts >= 4 s


# ----------------------------------------------------------------------------- item 4
def test_a_refused_frame_stamped_ahead_does_not_shut_out_the_genuine_one():
    """A forgery with the stamp of a frame KrakenSDR has not measured yet is refused (ahead of
    the autopilot's clock); the genuine frame with that stamp, when it comes, is used."""
    forged = frame(60.0, [[1.0]] * M, 99).encode()
    genuine = frame(60.0, [[0.2]] * M, 1).encode()
    served = [forged]
    with HostileServer(_serve(served)) as srv:
        clock = ManualClock(50.05)
        app = kraken_app(srv.url, clock)
        src = app.kraken.source
        try:
            assert wait_for(lambda: src.rejected["future_time"] == M, 10), src.rejected
            clock.t = 60.05
            served[0] = genuine
            assert wait_for(lambda: any(tk["t"] == 60.0 and tk["channels"] for tk in app.ticks), 10), (
                src.frames, src.repeated, src.rejected)
        finally:
            app.stop()
    assert src.frames == 1 and src.repeated == 0 and src.scans == M


# ----------------------------------------------------------------------------- item 10
def test_one_read_is_one_request_on_one_kept_alive_connection():
    with HostileServer(_serve([DOC])) as srv:  # HTTP/1.1, keeps the connection (as miniserve does)
        src = HttpSource(srv.url, kl.MAX_DOC_BYTES, timeout_s=1.0)
        for _ in range(20):
            assert src.get() == DOC
        src.close()
        assert (srv.requests, srv.connections) == (20, 1)
        assert (src.requests, src.retries) == (20, 0)
        poller = DocumentPoller(srv.url, None, 0.005, timeout_s=1.0).start()
        try:
            assert wait_for(lambda: poller.reads >= 50, 10)
        finally:
            poller.stop()
        assert srv.requests - 20 == poller.reads and srv.connections == 2 and not poller.errors
    # a server that closes each connection after its answer without saying so: every read still
    # answered, on a new connection, the retry counted
    with HostileServer(_serve([DOC], keep_alive=False)) as srv:
        src = HttpSource(srv.url, kl.MAX_DOC_BYTES, timeout_s=1.0)
        for _ in range(10):
            assert src.get() == DOC
            time.sleep(0.01)  # the server's close has come
        src.close()
        # (the request sent on the closed connection never reached the server)
        assert srv.connections == srv.requests == 10 and src.retries == 9 and src.requests == 19


# ----------------------------------------------------------------------------- a reader that fails
def test_a_reader_that_fails_is_restarted_and_says_so_once():
    """Whatever fails on the reader's thread (here its parser, made to raise on two documents),
    the thread is restarted, counted, said once; the next genuine frame is used."""
    served = [b""]  # an empty document: nothing read until the parser is in place
    with HostileServer(_serve(served)) as srv:
        clock = ManualClock(51.05)
        app = kraken_app(srv.url, clock)
        poller = app.kraken.poller
        parse = poller.prepare["doa"]

        def fragile(doc: bytes):
            if doc.startswith(b"BOOM"):
                raise RuntimeError("a parser bug")
            return parse(doc)

        poller.prepare["doa"] = fragile
        try:
            for k in (1, 2):
                served[0] = b"BOOM %d\n" % k
                assert wait_for(lambda: poller.restarts == k, 10), poller.restarts
            served[0] = frame(51.0, [[0.2]] * M, 1).encode()
            assert wait_for(lambda: any(tk["t"] == 51.0 and tk["channels"] for tk in app.ticks), 10)
            assert poller._thread.is_alive()
        finally:
            app.stop()
    said = [text for _, text in app.events if "reader failed" in text]
    assert said == ["PMON: KrakenSDR reader failed and was restarted (RuntimeError: a parser bug)"], said
    assert poller.restarts == 2
