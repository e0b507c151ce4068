"""The Zenoh key space of driveby (design.md), as functions that validate every chunk.

Concrete keys (``*_key``) take concrete ids only; key expressions (``*_keyexpr``) also
accept ``"*"`` where the design shards or subscribes by wildcard.  An id is
``[A-Za-z0-9_.-]+`` (at most 128 characters), so it can never smuggle a ``/``, a
wildcard ``*``, a ``$`` or a selector ``?`` into a key.

::

    driveby/<net>/veh/<vehicle>/imu                 raw sensor chunks (simfleet -> edge)
    driveby/<net>/ap/<route>/<tile>/<vehicle>       AP segments (edge -> cloud)
    driveby/<net>/done/<vehicle>                    end-of-pass markers (edge -> cloud)
    driveby/<net>/ack/<vehicle>                     pass acknowledgements (cloud -> run orchestrator)
    driveby/<net>/calib/<vehicle>                   calibration (cloud -> edge)
    driveby/<net>/state/profile/<route>/<tile>      queryable: tile posterior
    driveby/<net>/state/bridge/<bridge>             queryable: bridge posterior
    driveby/<net>/alarm/<bridge>                    bridge alarms
    driveby/<net>/alive/<role>/<id>                 liveliness tokens
"""

from __future__ import annotations

import re

ROOT = "driveby"
MAX_ID_LEN = 128
_ID_RE = re.compile(r"[A-Za-z0-9_.-]+")
_TILE_RE = re.compile(r"0|[1-9][0-9]*")
_VEHICLE_TOPICS = ("imu", "calib", "done", "ack")

__all__ = [
    "ROOT",
    "is_valid_id",
    "check_id",
    "imu_key",
    "imu_keyexpr",
    "ap_key",
    "ap_keyexpr",
    "parse_ap_key",
    "done_key",
    "done_keyexpr",
    "ack_key",
    "ack_keyexpr",
    "calib_key",
    "calib_keyexpr",
    "state_profile_key",
    "state_profile_keyexpr",
    "state_bridge_key",
    "state_bridge_keyexpr",
    "alarm_key",
    "alarm_keyexpr",
    "alive_key",
    "alive_keyexpr",
    "parse_alive_key",
    "parse_vehicle_key",
]


def is_valid_id(value: object) -> bool:
    """True if ``value`` is a string usable as one key chunk (``[A-Za-z0-9_.-]{1,128}``)."""
    return (
        isinstance(value, str)
        and 0 < len(value) <= MAX_ID_LEN
        and _ID_RE.fullmatch(value) is not None
    )


def check_id(value: object, what: str = "id") -> str:
    """Return ``value`` if it is a valid id, else raise ``ValueError`` naming ``what``."""
    if not is_valid_id(value):
        raise ValueError(f"invalid {what} {value!r}: expected [A-Za-z0-9_.-]{{1,{MAX_ID_LEN}}}")
    return value  # type: ignore[return-value]


def _check_tile(tile: object) -> int:
    if isinstance(tile, bool) or not isinstance(tile, int) or tile < 0:
        raise ValueError(f"invalid tile {tile!r}: expected an integer >= 0")
    return tile


def _id_or_star(value: object, what: str) -> str:
    return "*" if value == "*" else check_id(value, what)


def _join(*chunks: str) -> str:
    return "/".join((ROOT, *chunks))


# -- raw sensor streams -------------------------------------------------------------


def imu_key(net: str, vehicle: str) -> str:
    """``driveby/<net>/veh/<vehicle>/imu``: raw sensor chunks of one vehicle."""
    return _join(check_id(net, "net"), "veh", check_id(vehicle, "vehicle"), "imu")


def imu_keyexpr(net: str, vehicle: str = "*") -> str:
    """Raw sensor chunks of one vehicle or (``"*"``) of every vehicle."""
    return _join(check_id(net, "net"), "veh", _id_or_star(vehicle, "vehicle"), "imu")


# -- AP segments ----------------------------------------------------------------------


def ap_key(net: str, route: str, tile: int, vehicle: str) -> str:
    """``driveby/<net>/ap/<route>/<tile>/<vehicle>``: one AP segment's key."""
    return _join(
        check_id(net, "net"),
        "ap",
        check_id(route, "route"),
        str(_check_tile(tile)),
        check_id(vehicle, "vehicle"),
    )


def ap_keyexpr(net: str, route: str = "*", vehicle: str = "*") -> str:
    """Subscription for AP segments: ``driveby/<net>/ap/<route>/**``.

    ``route="*"`` takes every route (one aggregator per route is a shard). With a
    concrete ``vehicle`` the expression is ``driveby/<net>/ap/<route>/*/<vehicle>``.
    """
    head = _join(check_id(net, "net"), "ap", _id_or_star(route, "route"))
    if vehicle == "*":
        return head + "/**"
    return f"{head}/*/{check_id(vehicle, 'vehicle')}"


def parse_ap_key(key: object) -> tuple[str, str, int, str]:
    """Split an AP key into ``(net, route, tile, vehicle)``, validating every chunk.

    Raises
    ------
    ValueError
        If ``key`` is not exactly ``driveby/<net>/ap/<route>/<tile>/<vehicle>`` with
        valid ids and a canonical decimal tile.
    """
    if not isinstance(key, str):
        raise ValueError(f"AP key must be a string, got {type(key).__name__}")
    parts = key.split("/")
    if len(parts) != 6 or parts[0] != ROOT or parts[2] != "ap":
        raise ValueError(f"not an AP key: {key!r}")
    _, net, _, route, tile, vehicle = parts
    if _TILE_RE.fullmatch(tile) is None:
        raise ValueError(f"invalid tile chunk {tile!r} in {key!r}")
    return check_id(net, "net"), check_id(route, "route"), int(tile), check_id(vehicle, "vehicle")


# -- per-vehicle control topics -------------------------------------------------------


def done_key(net: str, vehicle: str) -> str:
    """``driveby/<net>/done/<vehicle>``: the edge's end-of-pass markers."""
    return _join(check_id(net, "net"), "done", check_id(vehicle, "vehicle"))


def done_keyexpr(net: str) -> str:
    """End-of-pass markers of every vehicle."""
    return _join(check_id(net, "net"), "done", "*")


def ack_key(net: str, vehicle: str) -> str:
    """``driveby/<net>/ack/<vehicle>``: the cloud's acknowledgement of a vehicle's passes."""
    return _join(check_id(net, "net"), "ack", check_id(vehicle, "vehicle"))


def ack_keyexpr(net: str) -> str:
    """Acknowledgements for every vehicle."""
    return _join(check_id(net, "net"), "ack", "*")


def calib_key(net: str, vehicle: str) -> str:
    """``driveby/<net>/calib/<vehicle>``: calibration published by the cloud for a vehicle."""
    return _join(check_id(net, "net"), "calib", check_id(vehicle, "vehicle"))


def calib_keyexpr(net: str) -> str:
    """Calibrations of every vehicle."""
    return _join(check_id(net, "net"), "calib", "*")


def parse_vehicle_key(key: object, topic: str) -> tuple[str, str]:
    """Split a per-vehicle key (``imu``, ``calib``, ``done``, ``ack``) into ``(net, vehicle)``.

    Used to check that a payload's ``vehicle_id`` is the one its key names.
    """
    if topic not in _VEHICLE_TOPICS:
        raise ValueError(f"unknown per-vehicle topic {topic!r}; one of {_VEHICLE_TOPICS}")
    if not isinstance(key, str):
        raise ValueError(f"key must be a string, got {type(key).__name__}")
    parts = key.split("/")
    if topic == "imu":
        ok = len(parts) == 5 and parts[2] == "veh" and parts[4] == "imu"
    else:
        ok = len(parts) == 4 and parts[2] == topic
    if not ok or parts[0] != ROOT:
        raise ValueError(f"not a {topic} key: {key!r}")
    return check_id(parts[1], "net"), check_id(parts[3], "vehicle")


# -- queryable state, alarms, liveliness ----------------------------------------------


def state_profile_key(net: str, route: str, tile: int) -> str:
    """``driveby/<net>/state/profile/<route>/<tile>``: queryable tile posterior."""
    return _join(
        check_id(net, "net"), "state", "profile", check_id(route, "route"), str(_check_tile(tile))
    )


def state_profile_keyexpr(net: str, route: str = "*") -> str:
    """Every tile posterior of one route (or of every route)."""
    return _join(check_id(net, "net"), "state", "profile", _id_or_star(route, "route"), "*")


def state_bridge_key(net: str, bridge: str) -> str:
    """``driveby/<net>/state/bridge/<bridge>``: queryable bridge posterior."""
    return _join(check_id(net, "net"), "state", "bridge", check_id(bridge, "bridge"))


def state_bridge_keyexpr(net: str) -> str:
    """Every bridge posterior."""
    return _join(check_id(net, "net"), "state", "bridge", "*")


def alarm_key(net: str, bridge: str) -> str:
    """``driveby/<net>/alarm/<bridge>``: alarms raised for a bridge."""
    return _join(check_id(net, "net"), "alarm", check_id(bridge, "bridge"))


def alarm_keyexpr(net: str) -> str:
    """Alarms of every bridge."""
    return _join(check_id(net, "net"), "alarm", "*")


def alive_key(net: str, role: str, id: str) -> str:  # noqa: A002 - the design's name
    """``driveby/<net>/alive/<role>/<id>``: key of a liveliness token (role: edge, cloud, ...)."""
    return _join(check_id(net, "net"), "alive", check_id(role, "role"), check_id(id, "id"))


def alive_keyexpr(net: str, role: str = "*") -> str:
    """Liveliness tokens of one role (or of every role)."""
    return _join(check_id(net, "net"), "alive", _id_or_star(role, "role"), "*")


def parse_alive_key(key: object) -> tuple[str, str, str]:
    """Split a liveliness key into ``(net, role, id)``, validating every chunk."""
    if not isinstance(key, str):
        raise ValueError(f"key must be a string, got {type(key).__name__}")
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[2] != "alive":
        raise ValueError(f"not a liveliness key: {key!r}")
    return check_id(parts[1], "net"), check_id(parts[3], "role"), check_id(parts[4], "id")


# -- control (the run orchestrator talking to its daemons) --------------------------------


def control_key(net: str, target: str, verb: str) -> str:
    """``driveby/<net>/control/<target>/<verb>``: a queryable a daemon answers (e.g. ``export``)."""
    return _join(check_id(net, "net"), "control", check_id(target, "target"), check_id(verb, "verb"))


def status_key(net: str, daemon: str) -> str:
    """``driveby/<net>/status/<daemon>``: a daemon's JSON status as it changes (e.g. calibration settled)."""
    return _join(check_id(net, "net"), "status", check_id(daemon, "daemon"))
