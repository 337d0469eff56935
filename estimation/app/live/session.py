"""Zenoh sessions as coopmap opens them: peers on TCP, no multicast scouting, a short lease.

The base listens on an endpoint (``tcp/127.0.0.1:7447`` by default: loopback only); robot agents
and viewers connect to it and keep trying while it is away, so a base that restarts is found
again. The lease decides how soon a frozen or unplugged process counts as gone (its liveliness
token disappears).
"""

from __future__ import annotations

import json
import re
from typing import Any

from estimation.app.live.wire import WireError

__all__ = ["DEFAULT_ENDPOINT", "LEASE_MS", "check_endpoint", "open_session"]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: A session that sent nothing for this long (ms) is dropped, with its liveliness tokens.
LEASE_MS = 2000
_ENDPOINT = re.compile(r"(tcp|udp|tls|quic)/(\[[0-9a-fA-F:]+\]|[A-Za-z0-9_.-]+):(\d{1,5})")


def check_endpoint(text: str) -> str:
    """``text`` if it is a Zenoh locator coopmap can use (``tcp/HOST:PORT``); WireError if not."""
    match = _ENDPOINT.fullmatch(text)
    if match is None or not 0 < int(match.group(3)) < 65536:
        raise WireError(f"endpoint {text!r}: expected PROTOCOL/HOST:PORT, e.g. {DEFAULT_ENDPOINT}")
    return text


def open_session(*, listen: list[str] | None = None, connect: list[str] | None = None,
                 lease_ms: int = LEASE_MS) -> Any:  # fmt: skip
    """A Zenoh peer session listening on and/or connecting to the given endpoints."""
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps([check_endpoint(e) for e in listen or []]))
    config.insert_json5("connect/endpoints",
                        json.dumps([check_endpoint(e) for e in connect or []]))  # fmt: skip
    config.insert_json5("transport/link/tx/lease", str(int(lease_ms)))
    config.insert_json5("transport/link/tx/keep_alive", "4")
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise WireError(f"cannot open a Zenoh session ({', '.join(listen or connect or [])}): "
                        f"{str(exc).splitlines()[0] if str(exc) else exc}") from None  # fmt: skip
