"""The autonomous coverage sweep: lanes over a plate whose size the robot finds by itself
with its IR edge sensors (the paper's Algorithm 1 detects the edges), capturing at the
spacing the camera's footprint and overlap require.

The route, in the robot's odometry frame (heading 0: the way it faces at the start):

1. drive ahead to the plate's edge and square up to it (the heading is reset there);
2. turn a quarter and drive to the side edge: the corner;
3. drive lanes back and forth, each from edge to edge, stepping one lane width away from
   the first side edge between them, until a step meets the far side edge; the last lane
   runs along it;
4. visit the holes: parts of the surface in view that no frame shows (a frame the camera
   lost, a stretch the operator drove by hand), largest first, and capture each.

Each lane ends where the front IR sensors see the edge, so the camera's footprint (which
reaches beyond the sensors) covers the band along every edge; the robot squares up to each
end edge, which corrects the heading its turns drift by. Turns happen a little back from
the edge so no wheel comes near it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from processing.coverage import CoverageParams, coverage_map
from processing.poses import wrap_angle

FRONT = (0, 1)  # front_left, front_right (IR_NAMES order)
EVERY_GAP = CoverageParams(min_hole_width=0.0)


class SweepStopped(Exception):
    """The operator stopped the sweep."""


class Pilot(Protocol):
    """What the sweep needs of the robot."""

    @property
    def pose(self) -> NDArray[np.float64]:
        """Odometry pose (x, y, heading)."""

    def ir_out(self) -> list[int]:
        """IR sensors that see no surface now."""

    def set_heading(self, heading: float) -> None:
        """Correct the odometry heading."""

    async def step(self, v: float, w: float) -> None:
        """Drive at (``v`` m/s, ``w`` rad/s) until the next sensor sample; waits while the
        sweep is paused; SweepStopped when it is stopped."""

    async def capture(self) -> None:
        """Take an inspection frame now."""

    def frame_footprints(self) -> list[NDArray[np.float64]]:
        """The surface (4, 2) each frame taken so far shows, odometry frame."""


@dataclass(frozen=True)
class SweepParams:
    """Speeds, the lane width and the turning geometry."""

    speed_mps: float = 0.12
    turn_radps: float = 0.6
    lane_width_m: float = 0.28  # the footprint across the heading times (1 - overlap)
    back_off_m: float = 0.03  # from an edge before turning
    creep_mps: float = 0.02  # onto an edge while squaring up
    square_radps: float = 0.1  # turning while squaring up
    first_turn: int = -1  # -1: the first quarter turn is to the left, +1: to the right
    heading_tolerance: float = 0.004  # rad
    max_square_swing: float = 0.35  # rad
    max_lanes: int = 200
    max_hole_visits: int = 20
    sensor_reach_m: float = 0.12  # how far ahead of the robot's centre the front IR sensors sit


@dataclass
class SweepProgress:
    """Where the sweep is, for telemetry and the dashboard."""

    phase: str = "starting"
    lanes_done: int = 0
    # odometry x, y of the edge point ahead of the robot at each edge it squared up to, and
    # the heading it faced
    edges_found: list[list[float]] = field(default_factory=list)
    holes_visited: int = 0
    # the lanes driven, [x0, y0, x1, y1] each, and the next one as planned (odometry frame)
    lanes: list[list[float]] = field(default_factory=list)
    next_lane: list[float] | None = None
    finished: bool = False


class CoverageSweep:
    """Runs the route on a :class:`Pilot`."""

    def __init__(self, pilot: Pilot, params: SweepParams) -> None:
        self.pilot = pilot
        self.p = params
        self.progress = SweepProgress()

    async def run(self) -> SweepProgress:
        """Sweep the plate; the progress when done."""
        p, turn = self.p, self.p.first_turn
        self.progress.phase = "finding the first edge"
        await self.pilot.capture()
        await self.to_edge(0.0)
        self.progress.phase = "finding the corner"
        await self.rotate_to(turn * math.pi / 2)
        await self.to_edge(turn * math.pi / 2)
        lane_heading = math.pi
        step_heading = -turn * math.pi / 2
        last = False
        for _ in range(p.max_lanes):
            self.progress.phase = f"lane {self.progress.lanes_done + 1}"
            await self.rotate_to(lane_heading)
            start = self.pilot.pose.copy()
            await self.to_edge(lane_heading, line=start)
            self._lane_done(start, step_heading)
            if last:
                break
            self.progress.phase = f"stepping to lane {self.progress.lanes_done + 1}"
            await self.rotate_to(step_heading)
            last = await self.drive(step_heading, p.lane_width_m)
            lane_heading = float(wrap_angle(lane_heading + math.pi))
        await self.visit_holes()
        self.progress.phase = "done"
        self.progress.next_lane = None
        self.progress.finished = True
        return self.progress

    async def visit_holes(self) -> None:
        """Drive to the centre of each hole in the frames' coverage of the plate as found and
        capture it there."""
        visited: list[tuple[float, float]] = []
        outline = self.plate_outline()
        if outline is None:
            return
        while len(visited) < self.p.max_hole_visits:
            footprints = self.pilot.frame_footprints()
            # every gap counts for the robot, slivers too: it is there to close them
            cover = coverage_map(
                footprints, [True] * len(footprints), EVERY_GAP, surface_outline=outline
            )
            # the robot drives to each hole's centroid and captures there
            spots = [
                h.centroid_m
                for h in cover.holes
                if all(
                    math.hypot(h.centroid_m[0] - vx, h.centroid_m[1] - vy) > 0.02
                    for vx, vy in visited
                )
            ]
            if not spots:
                return
            hx, hy = spots[0]
            visited.append((hx, hy))
            self.progress.holes_visited = len(visited)
            self.progress.phase = f"visiting hole {len(visited)} at x {hx:.2f} m, y {hy:.2f} m"
            x, y, _ = self.pilot.pose
            heading = math.atan2(hy - y, hx - x)
            await self.rotate_to(heading)
            await self.drive(heading, float(np.hypot(hx - x, hy - y)))
            await self.pilot.capture()

    async def to_edge(self, heading: float, line: NDArray[np.float64] | None = None) -> None:
        """Drive along ``heading`` (on the line through ``line``'s x, y when given) until the
        front sensors see the edge; square up, capture, back off."""
        origin = self.pilot.pose.copy() if line is None else line
        while not self._front_out():
            await self.pilot.step(self.p.speed_mps, self._steer(heading, origin))
        await self.pilot.step(0.0, 0.0)
        await self.square_up(heading)
        self._edge_found()
        await self.pilot.capture()
        await self.back_off()

    async def drive(self, heading: float, distance_m: float) -> bool:
        """Drive ``distance_m`` along ``heading``; True if an edge came first (then squared
        up, captured and backed off from)."""
        origin = self.pilot.pose.copy()
        while float(np.hypot(*(self.pilot.pose[:2] - origin[:2]))) < distance_m:
            if self._front_out():
                await self.pilot.step(0.0, 0.0)
                await self.square_up(heading)
                self._edge_found()
                await self.pilot.capture()
                await self.back_off()
                return True
            await self.pilot.step(self.p.speed_mps, self._steer(heading, origin))
        await self.pilot.step(0.0, 0.0)
        return False

    async def square_up(self, heading: float) -> None:
        """Square up to the edge ahead, whose normal is ``heading``, and reset the odometry
        heading to it: back until both front sensors see steel, creep up until one sees the
        edge (the creep keeps it on the edge's line), then turn towards that sensor until
        the other one sees the edge and back by half the swing (the two trip at mirrored
        angles)."""
        while self._front_out():
            await self.pilot.step(-self.p.creep_mps, 0.0)
        while not self._front_out():
            await self.pilot.step(self.p.creep_mps, 0.0)
        await self.pilot.step(0.0, 0.0)
        out = [i for i in FRONT if i in self.pilot.ir_out()]
        if len(out) == 2:
            self.pilot.set_heading(heading)
            return
        # turning towards the sensor that is out brings the other one forward
        direction = 1.0 if out[0] == 1 else -1.0
        other = FRONT[0] if out[0] == FRONT[1] else FRONT[1]
        start = float(self.pilot.pose[2])
        swing = 0.0
        while abs(swing) < self.p.max_square_swing:
            if other in self.pilot.ir_out():
                break
            await self.pilot.step(0.0, direction * self.p.square_radps)
            swing = float(wrap_angle(self.pilot.pose[2] - start))
        else:
            await self.rotate_to(start)  # a ragged edge: keep the heading as it was
            return
        await self.pilot.step(0.0, 0.0)
        await self.rotate_to(start + swing / 2)
        self.pilot.set_heading(heading)

    async def back_off(self) -> None:
        """Reverse ``back_off_m`` from the edge."""
        start = self.pilot.pose.copy()
        while float(np.hypot(*(self.pilot.pose[:2] - start[:2]))) < self.p.back_off_m:
            await self.pilot.step(-self.p.speed_mps / 2, 0.0)
        await self.pilot.step(0.0, 0.0)

    async def rotate_to(self, heading: float) -> None:
        """Turn in place to ``heading`` (odometry)."""
        for _ in range(3000):
            err = float(wrap_angle(heading - self.pilot.pose[2]))
            if abs(err) < self.p.heading_tolerance:
                break
            # slow down over the last 0.15 rad to stop on the heading
            rate = self.p.turn_radps * min(1.0, max(0.12, abs(err) / 0.15))
            await self.pilot.step(0.0, math.copysign(rate, err))
        await self.pilot.step(0.0, 0.0)

    def _lane_done(self, start: NDArray[np.float64], step_heading: float) -> None:
        """Record the lane from ``start`` to here and plan the next one a lane width along
        ``step_heading``."""
        end = self.pilot.pose
        lane = [round(float(v), 4) for v in (start[0], start[1], end[0], end[1])]
        self.progress.lanes.append(lane)
        self.progress.lanes_done += 1
        dx = self.p.lane_width_m * math.cos(step_heading)
        dy = self.p.lane_width_m * math.sin(step_heading)
        self.progress.next_lane = [
            round(v, 4) for v in (lane[2] + dx, lane[3] + dy, lane[0] + dx, lane[1] + dy)
        ]

    def plate_outline(self) -> NDArray[np.float64] | None:
        """The plate as found, (4, 2) corners in the odometry frame: its edges lie along the
        axes the first edge set (the robot squares up to each), so the extreme edge points
        met heading along each axis bound it. None before edges on all four sides."""
        pts = np.array(self.progress.edges_found, dtype=np.float64).reshape(-1, 3)
        axis = np.round(pts[:, 2] / (math.pi / 2)).astype(int) % 4  # 0: +x, 1: +y, 2: -x, 3: -y
        if len(set(axis.tolist())) < 4:
            return None
        x0, x1 = pts[axis == 2, 0].min(), pts[axis == 0, 0].max()
        y0, y1 = pts[axis == 3, 1].min(), pts[axis == 1, 1].max()
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])

    def _edge_found(self) -> None:
        x, y, yaw = self.pilot.pose
        reach = self.p.sensor_reach_m
        point = [
            round(float(x + reach * math.cos(yaw)), 4),
            round(float(y + reach * math.sin(yaw)), 4),
            round(float(yaw), 4),
        ]
        self.progress.edges_found.append(point)

    def _front_out(self) -> bool:
        return any(i in self.pilot.ir_out() for i in FRONT)

    def _steer(self, heading: float, origin: NDArray[np.float64]) -> float:
        """Turn rate that holds the line through ``origin`` along ``heading``."""
        x, y, yaw = self.pilot.pose
        normal = np.array([-math.sin(heading), math.cos(heading)])
        cross = float(normal @ (np.array([x, y]) - origin[:2]))
        yaw_err = float(wrap_angle(heading - yaw))
        return float(np.clip(3.0 * yaw_err - 8.0 * cross, -0.3, 0.3))
