"""Waiting on a cloud daemon's status messages (tests of real daemons over Zenoh)."""

from __future__ import annotations

import json
import threading

import zenoh

from shared import keys


def fused_event(session: zenoh.Session, net: str, cloud_id: str, passes: int) -> threading.Event:
    """An event set once the cloud's status says ``passes`` passes are acknowledged at their current
    calibration and fused as corrected (its idle work done): from then on its estimates change only
    with new input."""
    fused = threading.Event()

    def on_status(sample):
        try:
            st = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if st.get("passes_current") == passes and st.get("unfused_passes") == 0:
            fused.set()

    session.declare_subscriber(keys.status_key(net, cloud_id), on_status)
    return fused
