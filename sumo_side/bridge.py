"""From a SUMO snapshot to the wire message: look-ahead, paths, columns.

``Bridge.build`` is everything the SUMO side does per step besides SUMO's own
``simulationStep`` and the transport; the daemon and the benchmark share it so the
benchmark measures exactly what the daemon runs.
"""

from __future__ import annotations

import numpy as np

from protocol.messages import AgentBatch, StepMessage
from protocol.order import new_epoch
from sumo_side.config import SumoConfig
from sumo_side.lookahead import MODE_LANES, LookAhead, PathPlanner
from sumo_side.simulation import Snapshot, SumoSim


class Bridge:
    def __init__(self, sim: SumoSim, cfg: SumoConfig, run_id: str, epoch: int | None = None) -> None:
        """``epoch``: this incarnation of the run (SPEC 3.1.1; default: the time now)."""
        self.sim = sim
        self.epoch = new_epoch() if epoch is None else int(epoch)
        self.cfg = cfg
        self.run_id = run_id
        self.planner = PathPlanner(
            sim.graph, cfg.lad_min_m, cfg.lad_max_m, cfg.k_lad_s, cfg.path_length_m, reach_s=sim.step_length
        )
        self._last_serial = -1
        self._sent_version = -1  # static version whose vType table went out last

    def look_ahead(self, snap: Snapshot, with_paths: bool | None = None) -> LookAhead:
        # The snapshot's alignment is valid only against the snapshot planned before it.
        prev = snap.prev_index if snap.serial == self._last_serial + 1 else None
        self._last_serial = snap.serial
        seq = self.planner.update_sequences(
            snap.ids, snap.lane, snap.mode == MODE_LANES, self.sim.route_of, prev, snap.route_changed
        )
        return self.planner.compute(
            seq, snap.lane, snap.lane_pos, snap.x, snap.y, snap.angle, snap.speed, snap.mode,
            with_paths=self.cfg.path_ahead if with_paths is None else with_paths,
        )

    def build(
        self,
        step: int,
        snap: Snapshot,
        extra_flags: np.ndarray | None = None,
        with_paths: bool | None = None,
        final: bool = False,
    ) -> StepMessage:
        """The step message of ``snap`` (``extra_flags`` OR-ed in, e.g. the ego flags);
        ``final`` marks the run's last step."""
        look = self.look_ahead(snap, with_paths)
        vt = self.sim.vtypes
        f32 = np.float32
        flags = snap.flags if extra_flags is None else (snap.flags | extra_flags)
        agents = AgentBatch(
            ids=snap.ids,
            cls=vt.cls[snap.vtype],
            vtype=snap.vtype.astype(np.uint16),
            x=snap.x,
            y=snap.y,
            angle=snap.angle.astype(f32),
            speed=snap.speed.astype(f32),
            accel=snap.accel.astype(f32),
            signals=snap.signals.astype(np.uint16),
            la_x=look.la_xy[:, 0],
            la_y=look.la_xy[:, 1],
            length=vt.length[snap.vtype],
            width=vt.width[snap.vtype],
            lane=snap.lane.astype(np.int32),
            flags=flags.astype(np.uint8),
            path_offsets=look.path_offsets,
            path_xy=look.path_xy,
        )
        # The vType table goes out in the first step and whenever it changed (SPEC.md 3.1).
        sv = self.sim.static_version
        vtypes = None
        if sv != self._sent_version:
            vtypes = list(vt.types)
            self._sent_version = sv
        return StepMessage(
            run=self.run_id,
            step=int(step),
            time=snap.time,
            step_length=self.sim.step_length,
            agents=agents,
            tls=snap.tls,
            vtypes=vtypes,
            static_version=sv,
            final=final,
            epoch=self.epoch,
        )
