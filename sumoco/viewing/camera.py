"""A viewer's camera on Zenoh (SPEC 3.7): an interest point for the physics level of detail.

``CameraPublisher`` holds the camera's liveliness token for as long as it is open (so a
closed or dead viewer's camera is retired at once) and puts the ground point the camera
looks at. Callers put at ~2 Hz, also when the camera rests: the physics side drops a
camera it has not heard from for 5 s.
"""

from __future__ import annotations

import zenoh

from protocol.codec import encode
from protocol.keys import Keys
from protocol.messages import CameraPose

CAMERA_RATE_HZ = 2.0  # puts per second a viewer should send


class CameraPublisher:
    """Puts camera ``client`` of certificate role ``role`` (``viewer`` or ``renderer-<ego>``)."""

    def __init__(self, session: zenoh.Session, keys: Keys, client: str, role: str = "viewer") -> None:
        self.client = client
        self.key = keys.viewer_camera(role, client)  # checks both chunks
        self._pub = session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.DROP)
        self._token = session.liveliness().declare_token(keys.viewer_alive(role, client))
        self.closed = False

    def put(self, x: float, y: float, t: float = 0.0) -> None:
        """The ground point [m] the camera is centred on (SUMO network coordinates)."""
        self._pub.put(encode(CameraPose(self.client, float(x), float(y), float(t))))

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for d in (self._token, self._pub):
            try:
                d.undeclare()
            except Exception:  # the session went first
                pass

    def __enter__(self) -> "CameraPublisher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["CAMERA_RATE_HZ", "CameraPublisher"]
