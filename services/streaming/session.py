"""Opening zenoh sessions: peer mode on loopback by default, client mode against a zenohd router.

Multicast scouting is off unless asked for: it fails in containers and makes tests non-hermetic
(docs/ecosystem.md#zenoh). Peers find each other through explicit `listen` / `connect` endpoints.
"""

from __future__ import annotations

import argparse
import json
import re
from dataclasses import dataclass, field

import zenoh

from core.errors import N3dmapError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass(frozen=True)
class ZenohOptions:
    """How a process joins the zenoh network."""

    mode: str = "peer"                      # "peer" (embedded default) or "client" (against zenohd)
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    extra_json5: dict = field(default_factory=dict)  # path -> json5 value, for TLS/ACL settings

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client"):
            raise ValueError(f"zenoh mode must be 'peer' or 'client', got {self.mode!r}")
        if self.mode == "client" and not self.connect:
            raise ValueError("zenoh client mode needs at least one --connect ENDPOINT (the zenohd router)")

    def to_config(self) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        for path, value in self.extra_json5.items():
            conf.insert_json5(path, json.dumps(value))
        return conf


class ZenohSessionError(N3dmapError, ConnectionError):
    """A zenoh session could not open: a malformed endpoint, a taken listen port, no router to connect to."""


# zenoh's messages end in the Rust source location(s) of the error: " at /root/.cargo/.../x.rs:338."
_RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")


def open_session(options: ZenohOptions) -> zenoh.Session:
    """Open a zenoh session; a bad endpoint is a clear error naming it."""
    try:
        return zenoh.open(options.to_config())
    except zenoh.ZError as e:
        reason = " ".join(_RUST_LOCATION.sub("", str(e)).split())
        raise ZenohSessionError(f"cannot open zenoh session (mode={options.mode}, listen={list(options.listen)}, "
                                f"connect={list(options.connect)}): {reason}") from None


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, default_listen: bool) -> None:
    """The --mode/--connect/--listen options shared by `stream bridge|camera|listen`."""
    parser.add_argument("--mode", choices=("peer", "client"), default="peer",
                        help="peer: embedded, no router (default); client: connect to a zenohd router")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="endpoint to listen on (repeatable)"
                             + (f"; default {DEFAULT_ENDPOINT} in peer mode" if default_listen else ""))


def options_from_args(args: argparse.Namespace, *, default_listen: bool) -> ZenohOptions:
    listen = list(args.listen)
    connect = list(args.connect)
    if args.mode == "peer" and not listen and not connect:
        # The embedded default: the bridge listens on the well-known loopback endpoint and cameras
        # and listeners connect to it.
        if default_listen:
            listen = [DEFAULT_ENDPOINT]
        else:
            connect = [DEFAULT_ENDPOINT]
    return ZenohOptions(mode=args.mode, connect=tuple(connect), listen=tuple(listen))
