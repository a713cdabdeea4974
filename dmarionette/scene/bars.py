"""Control bars (paper §2.3): rigid frames carrying string attach points, and their motion.

A bar is not simulated: its pose over time comes from a :class:`BarTrajectory` (keyframes
with smooth interpolation, or a CSV file of timed poses) or, live, from a haptic device.
String attach points are fixed in the bar frame and moved with it every string step.

Rotations are given as XYZ Euler angles in degrees (roll about x, then pitch about y, then
yaw about z, all about the fixed world axes: ``R = Rz Ry Rx``); they are interpolated as
angles, which is smooth and exact for the tilts a puppeteer uses (well away from 90°).
"""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.rotations import euler_to_matrix
from dmarionette.scene.fields import SceneError, check_keys, read_float, read_str, read_table, read_vec3

__all__ = ["BarTrajectory", "ControlBar", "bar_attach_points", "read_bar_trajectory_csv"]


@dataclasses.dataclass(frozen=True)
class BarTrajectory:
    """A bar's pose over time: a C1 cubic Hermite spline through timed poses.

    Tangents are Catmull-Rom (central differences of the neighbouring keyframes) inside and
    zero at both ends, so the bar starts and stops at rest; before the first keyframe and
    after the last the pose is held.

    Attributes:
        times: keyframe times [s], strictly increasing, ``(K,)``.
        positions: bar centre positions [m], ``(K, 3)``.
        rotations: XYZ Euler angles [deg], ``(K, 3)``.
    """

    times: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray

    def __post_init__(self):
        t = np.asarray(self.times, dtype=np.float64)
        if t.ndim != 1 or len(t) < 1 or np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)):
            raise ValueError(f"bar keyframe times must be finite and strictly increasing; got {t.tolist()}")

    @classmethod
    def still(cls, position, rotation=(0.0, 0.0, 0.0)) -> BarTrajectory:
        """A bar that never moves."""
        return cls(np.array([0.0]), np.array([position], dtype=np.float64), np.array([rotation], dtype=np.float64))

    def _tangents(self, values: np.ndarray) -> np.ndarray:
        t = np.asarray(self.times)
        m = np.zeros_like(values)
        if len(t) > 2:
            m[1:-1] = (values[2:] - values[:-2]) / (t[2:] - t[:-2])[:, None]
        return m

    def _evaluate(self, values: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(self.times)
        query = np.clip(np.asarray(times, dtype=np.float64), t[0], t[-1])
        if len(t) == 1:
            return np.broadcast_to(values[0], (len(query), 3)).copy(), np.zeros((len(query), 3))
        m = self._tangents(values)
        i = np.clip(np.searchsorted(t, query, side="right") - 1, 0, len(t) - 2)
        span = t[i + 1] - t[i]
        u = ((query - t[i]) / span)[:, None]
        h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
        value = h00 * values[i] + h10 * span[:, None] * m[i] + h01 * values[i + 1] + h11 * span[:, None] * m[i + 1]
        d00, d10, d01, d11 = 6 * u**2 - 6 * u, 3 * u**2 - 4 * u + 1, -6 * u**2 + 6 * u, 3 * u**2 - 2 * u
        rate = (d00 * values[i] + d01 * values[i + 1]) / span[:, None] + d10 * m[i] + d11 * m[i + 1]
        held = (np.asarray(times) < t[0]) | (np.asarray(times) > t[-1])
        rate[held] = 0.0
        return value, rate

    def angles(self, times: np.ndarray) -> np.ndarray:
        """XYZ Euler angles [deg] at ``times``, ``(T, 3)`` (the interpolated keyframe angles)."""
        return self._evaluate(np.asarray(self.rotations, dtype=np.float64), times)[0]

    def pose(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bar centre position [m] ``(T, 3)``, velocity [m/s] ``(T, 3)`` and rotation ``(T, 3, 3)``."""
        position, velocity = self._evaluate(np.asarray(self.positions, dtype=np.float64), times)
        angles, _ = self._evaluate(np.asarray(self.rotations, dtype=np.float64), times)
        return position, velocity, euler_to_matrix(angles)


@dataclasses.dataclass(frozen=True)
class ControlBar:
    """A control bar: its attach points (bar frame) for the strings it carries, and its motion.

    Attributes:
        name: ``"main"`` or ``"hand"`` for the paper's bars (any name is allowed).
        attach: string name -> attach point in the bar frame [m].
        trajectory: the bar's pose over time.
    """

    name: str
    attach: Mapping[str, tuple[float, float, float]]
    trajectory: BarTrajectory

    def attach_points(self, times: np.ndarray, string_names: Sequence[str]) -> np.ndarray:
        """World positions [m] of the attach points of ``string_names`` at ``times``, ``(T, S, 3)``."""
        position, _, rotation = self.trajectory.pose(times)
        return bar_attach_points(position, rotation, [self.attach[name] for name in string_names])


def bar_attach_points(position: np.ndarray, rotation: np.ndarray, local) -> np.ndarray:
    """World positions [m] of attach points ``local`` ``(S, 3)`` (bar frame) of a bar at ``position``
    ``(..., 3)`` with ``rotation`` ``(..., 3, 3)``: ``(..., S, 3)``. The one formula the offline
    rollouts and the live loop use, so that a live session and its replay add the same numbers."""
    local = np.asarray(local, dtype=np.float64)
    return np.asarray(position)[..., None, :] + np.einsum("...ij,sj->...si", rotation, local)


def read_bar_trajectory_csv(path: str | Path) -> BarTrajectory:
    """Reads timed bar poses from a CSV file with the header ``t,x,y,z,rx,ry,rz``.

    Units: seconds, metres, degrees (XYZ Euler angles, see the module doc). Times must be
    strictly increasing. Errors name the file, the line and the column.
    """
    path = Path(path)
    columns = ["t", "x", "y", "z", "rx", "ry", "rz"]
    if not path.is_file():
        raise SceneError(str(path), "trajectory_file", str(path), "an existing CSV file of timed bar poses")
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or [c.strip() for c in reader.fieldnames] != columns:
            raise SceneError(str(path), "header", reader.fieldnames, f"the columns {','.join(columns)}")
        rows = []
        for line, row in enumerate(reader, start=2):
            try:
                values = [float(row[c]) for c in columns]
            except (TypeError, ValueError):
                raise SceneError(f"{path}: line {line}", "row", row, "seven numbers") from None
            if not np.all(np.isfinite(values)):
                raise SceneError(f"{path}: line {line}", "row", row, "finite numbers")
            rows.append(values)
    data = np.array(rows, dtype=np.float64).reshape(-1, 7)
    if len(data) == 0:
        raise SceneError(str(path), "rows", 0, "at least one timed pose")
    bad = np.nonzero(np.diff(data[:, 0]) <= 0)[0]
    if len(bad):
        raise SceneError(f"{path}: line {bad[0] + 3}", "t", data[bad[0] + 1, 0],
                         f"a time later than the previous one ({data[bad[0], 0]})")
    return BarTrajectory(data[:, 0], data[:, 1:4], data[:, 4:7])


def write_bar_trajectory_csv(path: str | Path, trajectory: BarTrajectory, times: np.ndarray) -> Path:
    """Samples ``trajectory`` at ``times`` into a CSV file that :func:`read_bar_trajectory_csv` reads."""
    path = Path(path)
    position, _, _ = trajectory.pose(times)
    angles = trajectory.angles(times)
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t", "x", "y", "z", "rx", "ry", "rz"])
        for t, p, a in zip(times, position, angles):
            writer.writerow([f"{t:.9g}", *(f"{v:.9g}" for v in p), *(f"{v:.9g}" for v in a)])
    return path


def bar_from_table(name: str, table: Mapping[str, Any], where: str, source_dir: Path) -> ControlBar:
    """Reads ``[bars.NAME]``: ``attach`` (string -> point), and ``keyframes`` or ``trajectory_file``."""
    check_keys(table, ["attach", "keyframes", "trajectory_file", "position", "rotation"], where)
    attach_table = read_table(table, "attach", where)
    attach = {key: read_vec3(attach_table, key, f"{where}.attach") for key in attach_table}
    if not attach:
        raise SceneError(where, "attach", {}, "at least one string attach point")
    if "trajectory_file" in table:
        if "keyframes" in table:
            raise SceneError(where, "keyframes", "...", "either keyframes or trajectory_file, not both")
        file = Path(read_str(table, "trajectory_file", where))
        trajectory = read_bar_trajectory_csv(file if file.is_absolute() else source_dir / file)
    elif "keyframes" in table:
        frames = table["keyframes"]
        if not isinstance(frames, list) or not frames or not all(isinstance(k, Mapping) for k in frames):
            raise SceneError(where, "keyframes", frames, "one or more [[bars.NAME.keyframes]] tables")
        times, positions, rotations = [], [], []
        for i, frame in enumerate(frames):
            w = f"{where}.keyframes #{i + 1}"
            check_keys(frame, ["t", "position", "rotation"], w)
            times.append(read_float(frame, "t", w, minimum=0.0))
            positions.append(read_vec3(frame, "position", w))
            rotations.append(read_vec3(frame, "rotation", w, (0.0, 0.0, 0.0)))
            if i and times[-1] <= times[-2]:
                raise SceneError(w, "t", times[-1], f"a time later than the previous keyframe's ({times[-2]})")
        trajectory = BarTrajectory(np.array(times), np.array(positions), np.array(rotations))
    else:
        trajectory = BarTrajectory.still(read_vec3(table, "position", where),
                                         read_vec3(table, "rotation", where, (0.0, 0.0, 0.0)))
    return ControlBar(name=name, attach=attach, trajectory=trajectory)
