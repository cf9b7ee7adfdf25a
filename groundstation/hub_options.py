"""``pmon gcs hub`` options and what they configure (groundstation/hub.py), light enough to
import when the CLI builds its parser."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field


@dataclass(frozen=True)
class HubConfig:
    """What the hub serves (``pmon gcs hub`` options; docs/OPERATING.md)."""

    serve: tuple[tuple[str, int], ...] = (("127.0.0.1", 14560),)  # UDP ports clients send to first
    out: tuple[tuple[str, int], ...] = ()  # UDP ports of clients that listen (QGC, MP: 14550)
    adsb: bool = True  # targets as ADSB_VEHICLE to the MAVLink clients
    circles: bool = True  # and their 1-sigma circle as an OA_DB item (Mission Planner, MAVProxy)
    tak_url: str | None = None  # CoT to TAK: udp://, tcp://, tls:// (pytak's COT_URL)
    tak_proto: int = 0  # 0: CoT XML, 1: TAK protobuf
    tak_tls: dict = field(default_factory=dict)  # PYTAK_TLS_* settings
    lost_after_s: float = 15.0  # no DF scan for this long: the target is lost (QGC ignores older tslc)
    stale_s: float = 10.0  # a CoT event is stale this long after it was sent, at most
    view_port: int | None = None


TAK_SCHEMES = {"udp": {"wo", "broadcast"}, "tcp": {"wo"}, "tls": {"wo"}}  # base: the modifiers pytak reads
TLS_FILES = ("PYTAK_TLS_CLIENT_CERT", "PYTAK_TLS_CLIENT_KEY", "PYTAK_TLS_CLIENT_CAFILE")


def check_url(url: str) -> None:
    """ValueError unless ``url`` is udp://, tcp:// or tls:// HOST:PORT (pytak's COT_URL forms
    the hub supports, with the modifiers of ``TAK_SCHEMES``), HOST by argcheck.host_name, PORT
    ASCII digits. pytak takes any scheme containing "udp" for UDP (``udp+log://stderr:1`` made
    it resolve "stderr"): the scheme is matched whole here."""
    from onboard.argcheck import host_port
    form = f"{url!r} is not udp://HOST:PORT, tcp://HOST:PORT or tls://HOST:PORT"
    scheme, sep, rest = url.partition("://")
    base, *mods = scheme.lower().split("+")
    if not sep or base not in TAK_SCHEMES or not set(mods) <= TAK_SCHEMES[base] or len(set(mods)) != len(mods):
        raise ValueError(form)
    if "/" in rest.rstrip("/") or "@" in rest or "?" in rest or "#" in rest:
        raise ValueError(form)
    hostport = rest.rstrip("/")
    if hostport.startswith("["):  # [IPv6]:PORT
        host, close, port = hostport[1:].partition("]")
        hostport = f"{host}{port}" if close and port.startswith(":") else ""
    try:
        host_port(hostport)
    except ValueError as exc:
        raise ValueError(f"{form}: {exc}") from None


def check_tls(url: str, tls: dict) -> None:
    """A tls:// URL's certificate, key and CA: each a readable regular file, the certificate
    given, PEM ones loadable (a bad one otherwise fails only in pytak's thread, after the hub
    started). ValueError naming the setting and the file."""
    from onboard.argcheck import readable_file
    if not url.lower().startswith("tls"):
        return
    if not tls.get("PYTAK_TLS_CLIENT_CERT"):
        raise ValueError("tls:// needs a client certificate: --tak-cert PEM (or PYTAK_TLS_CLIENT_CERT)")
    for name in TLS_FILES:
        if tls.get(name):
            readable_file(tls[name])
    cert, key, ca = (tls.get(n) for n in TLS_FILES)
    import ssl
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    password = tls.get("PYTAK_TLS_CERT_ENROLLMENT_PASSPHRASE", tls.get("PYTAK_TLS_CLIENT_PASSWORD")) or ""
    try:
        if not cert.endswith(".p12"):  # pytak converts PKCS#12 itself
            # a callable: an encrypted key without a password fails here, never prompts on the terminal
            ctx.load_cert_chain(cert, key or None, password=lambda: password.encode())
    except (ssl.SSLError, OSError) as exc:
        raise ValueError(f"{cert}{' / ' + key if key else ''}: not a PEM certificate and key that belong "
                         f"together ({getattr(exc, 'reason', None) or exc.strerror or exc})") from None
    try:
        if ca:
            ctx.load_verify_locations(cafile=ca)
    except (ssl.SSLError, OSError) as exc:
        raise ValueError(f"{ca}: not a PEM CA certificate ({getattr(exc, 'reason', None) or exc.strerror or exc})") \
            from None


def parse_udp(text: str, destination: bool = False) -> tuple[str, int]:
    """``udp:HOST:PORT`` or ``HOST:PORT`` -> (host, port); ValueError naming the problem. Port 0
    (any free one) only where the hub binds (``--serve``), never for a ``destination``."""
    from onboard.argcheck import host_port
    body = text[4:] if text.startswith("udp:") else text
    try:
        return host_port(body, any_port=not destination)
    except ValueError as exc:
        raise ValueError(f"{text!r} is not udp:HOST:PORT ({exc})") from None


def add_arguments(p) -> None:
    """``pmon gcs hub`` options (groundstation/cli.py)."""
    p.add_argument("--serve", action="append", metavar="udp:HOST:PORT",
                   help="listen for MAVLink clients here (repeatable; default udp:127.0.0.1:14560; "
                        "'none': no listening port)")
    p.add_argument("--out", action="append", metavar="udp:HOST:PORT", default=[],
                   help="send to a MAVLink client that listens (repeatable), e.g. QGroundControl or "
                        "Mission Planner on udp:127.0.0.1:14550")
    p.add_argument("--no-adsb", action="store_true", help="do not send the targets as ADSB_VEHICLE")
    p.add_argument("--no-circles", action="store_true",
                   help="do not send the targets' 1-sigma circles (ADSB_VEHICLE OA_DB items)")
    p.add_argument("--tak", metavar="URL", help="send CoT to TAK: udp://HOST:PORT (unicast or multicast), "
                   "tcp://HOST:PORT, tls://HOST:PORT (default: off)")
    p.add_argument("--tak-protobuf", action="store_true", help="TAK protocol 1 (protobuf) instead of CoT XML")
    from onboard.argcheck import IN_FILE, PORT_BIND
    p.add_argument("--tak-cert", metavar="PEM", type=IN_FILE, help="tls://: the client certificate (PYTAK_TLS_CLIENT_CERT)")
    p.add_argument("--tak-key", metavar="PEM", type=IN_FILE, help="tls://: its key (PYTAK_TLS_CLIENT_KEY)")
    p.add_argument("--tak-ca", metavar="PEM", type=IN_FILE, help="tls://: the TAK server's CA (PYTAK_TLS_CLIENT_CAFILE)")
    p.add_argument("--lost-after", type=float, default=15.0, metavar="S",
                   help="a target without a DF scan for S seconds is lost: its traffic and CoT expire (default 15)")
    p.add_argument("--view", type=PORT_BIND, metavar="PORT", help="also serve the live view on 127.0.0.1:PORT")
    p.add_argument("--duration", type=float, help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--scenario", default="paper", help="the mission's scenario: its geodetic origin "
                   "(name or YAML file; default paper)")


def config_from_args(args) -> HubConfig:
    """The options as a HubConfig; ValueError with the option's name on bad values."""
    serve = args.serve if args.serve is not None else ["udp:127.0.0.1:14560"]
    try:
        served = tuple(parse_udp(s) for s in serve if s != "none")
        outs = tuple(parse_udp(s, destination=True) for s in args.out)
    except ValueError as exc:
        raise ValueError(f"hub: --serve/--out: {exc}") from None
    if not served and not outs and not args.tak and args.view is None:
        raise ValueError("hub: nothing to serve: give --serve, --out, --tak or --view")
    if args.tak:
        try:
            check_url(args.tak)
        except ValueError as exc:
            raise ValueError(f"hub: --tak: {exc}") from None
    if not (math.isfinite(args.lost_after) and 1.0 <= args.lost_after <= 255.0):
        raise ValueError(f"hub: --lost-after must be in [1, 255] s, got {args.lost_after:g}")
    if args.duration is not None and not args.duration > 0:
        raise ValueError("hub: --duration must be > 0")
    tls = {k: v for k, v in os.environ.items() if k.startswith("PYTAK_TLS_")}
    tls.update({k: v for k, v in zip(TLS_FILES, (args.tak_cert, args.tak_key, args.tak_ca)) if v})
    if args.tak:
        try:
            check_tls(args.tak, tls)
        except ValueError as exc:
            raise ValueError(f"hub: --tak {args.tak}: {exc}") from None
    return HubConfig(served, outs, not args.no_adsb, not args.no_circles, args.tak, 1 if args.tak_protobuf else 0,
                     tls, args.lost_after, view_port=args.view)


