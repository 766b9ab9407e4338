"""The Zenoh configuration of every armfusion node: loopback only, no scouting.

Every node builds its :class:`zenoh.Config` here, from the shipped ``config/zenoh.json5``
(package data: :mod:`armfusion.fusion.shipped`) or another JSON5 file, with explicit overrides from
its command line::

    settings = ZenohSettings(listen=("tcp/127.0.0.1:0",), connect=("tcp/127.0.0.1:7447",))
    with open_session(settings) as session:
        ...

Whatever the file says, multicast and gossip scouting are switched off, and every listen
and connect endpoint (``tcp/``, ``tls/``, ``udp/``, ``quic/``, ``ws/``) must be a literal
loopback address (``127.0.0.0/8`` or ``[::1]``):
anything else is refused, with every offending endpoint named, before a session opens.
A peer or router with no listen endpoint would listen on every interface, so one is
required.
"""

from __future__ import annotations

import ipaddress
import json
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from armfusion.fusion.shipped import shipped_config

DEFAULT_CONFIG_PATH = shipped_config("zenoh.json5")
DEPLOY_CONFIG_DIR = shipped_config("deploy")
"""The deployment example: router.json5 (base station), chair.json5, base.json5 (TLS, ACL)."""
MODES = ("peer", "client", "router")
LOCATOR_PROTOCOLS = ("tcp", "udp", "quic", "tls", "ws")
"""Protocols whose endpoint is ``proto/host:port``; others (unix sockets…) are refused."""


class ZenohConfigError(ValueError):
    """The Zenoh configuration is not loopback-only, or cannot be read."""


@dataclass(frozen=True)
class ZenohSettings:
    """Where a node's Zenoh configuration comes from, and its explicit overrides.

    ``listen`` / ``connect``: endpoints such as ``tcp/127.0.0.1:7447`` replacing the
    file's (``None`` keeps the file's); ``mode``: ``peer``, ``client`` or ``router``.
    """

    config_path: Path | str | None = None
    listen: Sequence[str] | None = None
    connect: Sequence[str] | None = None
    mode: str | None = None
    extra: Mapping[str, Any] | None = None
    """Other keys to set, path to JSON value, e.g. the certificates of a TLS deployment:
    ``{"transport/link/tls/root_ca_certificate": "/etc/armfusion/tls/ca.pem"}``. Applied
    before the checks: they cannot switch scouting on or add a non-loopback endpoint."""


def endpoint_problem(endpoint: str) -> str | None:
    """Why ``endpoint`` is not a loopback endpoint, or ``None`` when it is."""
    if not isinstance(endpoint, str):
        return f"{endpoint!r}: not a string"
    locator = endpoint.split("?", 1)[0].split("#", 1)[0]
    proto, sep, address = locator.partition("/")
    if not sep or proto not in LOCATOR_PROTOCOLS:
        return (f"{endpoint!r}: expected <protocol>/<address>:<port> with protocol one of "
                f"{', '.join(LOCATOR_PROTOCOLS)}")
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return f"{endpoint!r}: expected <protocol>/<address>:<port>"
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return f"{endpoint!r}: {host!r} is not a literal IP address; use 127.0.0.1"
    if not ip.is_loopback:
        return f"{endpoint!r}: {host} is not a loopback address; armfusion only uses 127.0.0.1"
    return None


def check_loopback(endpoints: Sequence[str], what: str) -> None:
    """Raise :class:`ZenohConfigError` naming every endpoint of ``endpoints`` that is not loopback."""
    problems = [p for e in endpoints if (p := endpoint_problem(e)) is not None]
    if problems:
        raise ZenohConfigError(f"{what}: refused, not loopback: " + "; ".join(problems))


def _endpoints(config: zenoh.Config, key: str) -> list[str]:
    """The endpoints at ``key``: a list, or a per-mode object of lists."""
    value = json.loads(config.get_json(key))
    if value is None:
        return []
    if isinstance(value, dict):
        return [e for v in value.values() for e in (v or [])]
    return list(value)


def load_config(settings: ZenohSettings | None = None) -> zenoh.Config:
    """The node's :class:`zenoh.Config`: the file, the overrides, scouting off, checked loopback."""
    settings = settings or ZenohSettings()
    path = Path(settings.config_path) if settings.config_path is not None else DEFAULT_CONFIG_PATH
    if not path.is_file():
        raise ZenohConfigError(f"Zenoh config not found: {path}")
    try:
        config = zenoh.Config.from_file(str(path))
    except Exception as e:  # zenoh raises its own ZError for a bad file
        raise ZenohConfigError(f"{path}: cannot read the Zenoh config: {e}") from e
    if settings.mode is not None:
        if settings.mode not in MODES:
            raise ZenohConfigError(f"mode {settings.mode!r}: expected one of {', '.join(MODES)}")
        config.insert_json5("mode", json.dumps(settings.mode))
    for key, value in (settings.extra or {}).items():
        try:
            config.insert_json5(key, json.dumps(value))
        except Exception as e:  # zenoh raises its own ZError for an unknown key or a bad value
            raise ZenohConfigError(f"{path}: cannot set {key} = {value!r}: {e}") from e
    for key, override in (("listen/endpoints", settings.listen), ("connect/endpoints", settings.connect)):
        if override is not None:
            check_loopback(list(override), f"{key} override")
            config.insert_json5(key, json.dumps(list(override)))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    mode = json.loads(config.get_json("mode"))
    listen = _endpoints(config, "listen/endpoints")
    check_loopback(listen, f"{path}: listen/endpoints")
    check_loopback(_endpoints(config, "connect/endpoints"), f"{path}: connect/endpoints")
    if mode != "client" and not listen:
        raise ZenohConfigError(
            f"{path}: a {mode} with no listen endpoint would listen on every interface; "
            "give one, e.g. tcp/127.0.0.1:0")
    return config


def endpoints_line(config: zenoh.Config, settings: ZenohSettings | None = None) -> str:
    """Where a session of ``config`` listens and connects, and where each list came from
    (the file, or the command line's override in ``settings``), for a node to say at start."""
    settings = settings or ZenohSettings()
    path = settings.config_path if settings.config_path is not None else DEFAULT_CONFIG_PATH
    mode = json.loads(config.get_json("mode"))

    def part(verb: str, key: str, override: Sequence[str] | None) -> str:
        eps = _endpoints(config, key)
        source = path if override is None else "the command line"
        return f"{verb} {', '.join(eps) if eps else 'nothing'} ({source})"

    return (f"zenoh {mode}: {part('listening on', 'listen/endpoints', settings.listen)}; "
            f"{part('connecting to', 'connect/endpoints', settings.connect)}")


@contextmanager
def open_session(settings: ZenohSettings | None = None) -> Iterator[zenoh.Session]:
    """A Zenoh session from :func:`load_config`, closed when the ``with`` block ends."""
    config = load_config(settings)
    with zenoh.open(config) as session:
        yield session
