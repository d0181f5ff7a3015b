"""Foxglove 3D scene channel for recordings (``foxglove.SceneUpdate``, protobuf).

Opened in Foxglove, a recording shows the road network as lines, SUMO's reference
footprints as translucent boxes and every physics instance's actual agents as solid
boxes, plus the look-ahead points as red spheres (the paper's debugging spheres).
Scene frame ``map``: x east, y north, z up, the SUMO network frame.
"""

from __future__ import annotations

import numpy as np

from protocol.frames import front_to_centre, sumo_angle_to_yaw
from protocol.messages import PhysicsState, StaticData, StepMessage

try:  # foxglove-sdk is optional: recordings work without the scene channel
    import foxglove.messages as fm
except ImportError:  # pragma: no cover
    fm = None

SCENE_TOPIC = "/scene"
FRAME = "map"
_HEIGHT = {0: 1.5, 1: 1.5, 2: 3.0, 3: 1.7, 4: 1.8, 5: 2.5}  # [m] box height per agent class
_COLORS = {
    "sumo": (0.9, 0.2, 0.2, 0.35),
    "paper": (0.2, 0.4, 0.9, 0.9),
    "default": (0.2, 0.7, 0.3, 0.9),
}


def available() -> bool:
    return fm is not None


def schema() -> tuple[str, str, bytes]:
    s = fm.SceneUpdate.get_schema()
    return s.name, s.encoding, bytes(s.data)


def _ts(t: float):
    sec = int(t)
    return fm.Timestamp(sec=sec, nsec=int((t - sec) * 1e9))


def _boxes(x, y, angle, length, width, cls, color) -> list:
    yaw = sumo_angle_to_yaw(angle)
    cx, cy = front_to_centre(np.asarray(x, float), np.asarray(y, float), yaw, length)
    h = np.array([_HEIGHT.get(int(c), 1.5) for c in cls])
    qz, qw = np.sin(yaw / 2), np.cos(yaw / 2)
    col = fm.Color(r=color[0], g=color[1], b=color[2], a=color[3])
    return [
        fm.CubePrimitive(
            pose=fm.Pose(position=fm.Vector3(x=float(cx[i]), y=float(cy[i]), z=float(h[i] / 2)),
                         orientation=fm.Quaternion(x=0.0, y=0.0, z=float(qz[i]), w=float(qw[i]))),
            size=fm.Vector3(x=float(length[i]), y=float(width[i]), z=float(h[i])),
            color=col,
        )
        for i in range(len(cx))
    ]


def step_scene(msg: StepMessage) -> bytes:
    a = msg.agents
    spheres = [
        fm.SpherePrimitive(
            pose=fm.Pose(position=fm.Vector3(x=float(a.la_x[i]), y=float(a.la_y[i]), z=0.3),
                         orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            size=fm.Vector3(x=0.5, y=0.5, z=0.5), color=fm.Color(r=1.0, g=0.0, b=0.0, a=1.0))
        for i in range(a.n) if a.cls[i] != 4
    ]
    ent = fm.SceneEntity(
        timestamp=_ts(msg.time), frame_id=FRAME, id="sumo",
        cubes=_boxes(a.x, a.y, a.angle, a.length, a.width, a.cls, _COLORS["sumo"]),
        spheres=spheres,
    )
    return fm.SceneUpdate(entities=[ent]).encode()


def physics_scene(msg: PhysicsState, instance: str, lengths: dict[str, tuple[float, float]]) -> bytes:
    """``lengths`` maps agent id -> (length, width) from the latest SUMO step."""
    a = msg.agents
    lw = np.array([lengths.get(i, (4.5, 1.8)) for i in a.ids], float).reshape(-1, 2)
    ent = fm.SceneEntity(
        timestamp=_ts(msg.time), frame_id=FRAME, id=f"physics/{instance}",
        cubes=_boxes(a.x, a.y, a.heading, lw[:, 0], lw[:, 1], a.cls,
                     _COLORS.get(instance, (0.5, 0.5, 0.5, 0.9))),
    )
    return fm.SceneUpdate(entities=[ent]).encode()


def network_scene(static: StaticData) -> bytes:
    ln = static.lanes
    lines = []
    for i in range(len(ln.ids)):
        pts = ln.shape_xy[ln.shape_offsets[i]:ln.shape_offsets[i + 1]]
        if len(pts) < 2:
            continue
        lines.append(fm.LinePrimitive(
            type=fm.LinePrimitiveLineType.LineStrip, thickness=float(ln.width[i]),
            scale_invariant=False,
            points=[fm.Point3(x=float(p[0]), y=float(p[1]), z=0.0) for p in pts],
            color=fm.Color(r=0.35, g=0.35, b=0.38, a=1.0),
        ))
    ent = fm.SceneEntity(timestamp=_ts(0.0), frame_id=FRAME, id="network", lines=lines)
    return fm.SceneUpdate(entities=[ent]).encode()
