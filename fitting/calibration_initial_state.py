"""The shooting windows' start states as optional unknowns (docs/calibration.md, "Initial states").

``dmarionette calibrate --fit-initial-state`` refines the puppet state each window of the last
multiple-shooting stage starts from (:mod:`fitting.calibration_windows`): every window but the
first, ``a > 0``, starts from the *recorded* ``joint_q`` at frame ``a`` and the velocity that maps
frame ``a - 1`` to it. A recording is noisy (motion capture), and a velocity differenced from two
noisy frames a puppet step apart is noisier still (``sqrt(2) sigma_q / H``): a window started from
it drifts from the data, whatever the constants. Here each such start is ``q_a (+) dq`` with
velocity ``qd_a + dqd`` (``(+)``: :func:`retract`, on the joints' tangent space), ``dq`` and ``dqd``
``(qd_count,)`` each fitted with the constants, with a Gaussian prior of the recording noise:
``sigma_q`` (``--noise-joint``, rad for rotations and m for the root's translation) and
``sigma_qd = sqrt(2) sigma_q / H``. They are fitted in units of their prior deviations (so the
prior rows are the unknowns themselves, one per unknown, unit variance).

**Why per window, not the session's start**: the windows' starts are the only states taken from
the recording; the session's own start (window 0) is the scene's rest state, from which the
simulator and the live loop start (and the strings with it, straight and at rest), so it is not
refined. One rollout (``--window 0``) takes nothing from the recording: refused.

**The Jacobian** (``lm-fd``): a window's start state moves that window's residuals, and later
windows' only through the strings handed over (their tied ends are moved to the refined body
points, so only the strings' shape and tie forces carry it). That coupling is neglected: the
unknown ``i`` of *every* window is perturbed in one rollout and each window's rows are assigned to
its own unknown (``2 qd_count`` rollouts per linearisation whatever the number of windows, instead
of ``2 qd_count`` per window). The residuals themselves are exact, so the optimum is the right
one; the intervals use the approximate Jacobian. The unknowns are nuisance parameters: they are
not judged for identifiability (their prior determines them), and the constants' intervals
include their uncertainty.
"""

from __future__ import annotations

import numpy as np

__all__ = ["InitialStateUnknowns", "retract"]


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions ``(w, x, y, z)``."""
    return np.concatenate([[a[0] * b[0] - a[1:] @ b[1:]], a[0] * b[1:] + b[0] * a[1:] + np.cross(a[1:], b[1:])])


def retract(topology, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """``q (+) dq``: coordinates ``(q_count,)`` moved by a tangent vector ``(qd_count,)`` the way the
    puppet's integrator moves them by ``H qd`` (free joint: world translation, then body-frame
    rotation ``r exp(dq / 2)``; ball: the rotation; universal and hinge: added)."""
    out = np.array(q, dtype=np.float64)
    for j in topology.joints:
        s, d = j.q_start, j.qd_start
        if j.type in ("free", "ball"):
            o = 0
            if j.type == "free":
                out[s:s + 3] = q[s:s + 3] + dq[d:d + 3]
                o = 3
            v = np.asarray(dq[d + o:d + o + 3], dtype=np.float64)
            angle = np.linalg.norm(v)
            step = np.array([1.0, 0.0, 0.0, 0.0]) if angle == 0.0 else \
                np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * v / angle])
            r = q[s + o:s + o + 4] / np.linalg.norm(q[s + o:s + o + 4])
            out[s + o:s + o + 4] = _quat_mul(r, step)
        else:
            count = {"universal": 2, "hinge": 1}[j.type]
            out[s:s + count] = q[s:s + count] + dq[d:d + count]
    return out


class InitialStateUnknowns:
    """The start-state corrections of windows ``a > 0`` as a block of the parameter vector.

    Args:
        windows: the last stage's windows ``[(a, b), ...]`` (puppet frames).
        qd_count: the puppet's velocity coordinates.
        sigma_q: the recorded ``joint_q``'s noise (rad, m); ``puppet_dt``: ``H`` [s].
        offset: where the block starts in ``theta``.
        rows_of: target -> ``(start, stop)`` of its data rows; ``per_step``: target -> rows per
            puppet frame (bodies) or per string step (feedback); ``substeps``: string steps per frame.
        prior_start: the row of the first prior row of this block.
    """

    def __init__(self, windows, qd_count: int, sigma_q: float, puppet_dt: float, offset: int,
                 rows_of: dict, per_step: dict, substeps: int, prior_start: int):
        if not (np.isfinite(sigma_q) and sigma_q > 0):
            raise ValueError(f"--noise-joint: got {sigma_q!r}; expected a positive noise scale of the recorded "
                             "joint_q (rad, m)")
        self.starts = [a for a, _ in windows[1:]]
        self.qd_count = qd_count
        self.per_window = 2 * qd_count
        self.count = len(self.starts) * self.per_window
        self.sigma_q, self.sigma_qd = float(sigma_q), float(np.sqrt(2.0) * sigma_q / puppet_dt)
        self.offset, self.prior_start = offset, prior_start
        self.puppet_dt = puppet_dt
        window_of_frame = np.zeros(windows[-1][1] + 1, dtype=int)
        for w, (a, b) in enumerate(windows):
            window_of_frame[a + 1:b + 1] = w
        rows = []
        for target, (start, stop) in rows_of.items():
            if target == "bodies":
                frames = np.arange(stop - start) // per_step[target] + 1
            else:  # string step k (0-based) ends in puppet frame k // substeps + 1
                frames = (np.arange(stop - start) // per_step[target]) // substeps + 1
            rows.append(window_of_frame[np.minimum(frames, len(window_of_frame) - 1)])
        self.row_window = np.concatenate(rows) if rows else np.zeros(0, int)

    def units(self) -> np.ndarray:
        """Each unknown's unit (its prior deviation), ``(count,)``."""
        one = np.concatenate([np.full(self.qd_count, self.sigma_q), np.full(self.qd_count, self.sigma_qd)])
        return np.tile(one, len(self.starts))

    def labels(self) -> list[str]:
        return [f"{kind}[t={a * self.puppet_dt:.4g}s][{i}]" for a in self.starts for kind in ("dq", "dqd")
                for i in range(self.qd_count)]

    def refine(self, theta: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """``{a: (dq, dqd)}`` at ``theta``."""
        block = (np.asarray(theta[self.offset:self.offset + self.count]) * self.units()).reshape(
            len(self.starts), 2, self.qd_count)
        return {a: (block[w, 0], block[w, 1]) for w, a in enumerate(self.starts)}

    def prior_rows(self, theta: np.ndarray) -> np.ndarray:
        """The prior's rows: the unknowns in their prior deviations, ``(count,)``."""
        return np.asarray(theta[self.offset:self.offset + self.count], dtype=np.float64)

    def colored_columns(self, residuals, theta: np.ndarray, value: np.ndarray, step: float,
                        central: bool) -> np.ndarray:
        """The Jacobian's columns of the block ``(m, count)`` from ``2 qd_count`` rollouts
        (``4 qd_count`` central): unknown ``i`` of every window perturbed at once, each window's
        data rows (and each unknown's prior row) assigned to its own unknown (module doc)."""
        m = len(value)
        out = np.zeros((m, self.count))
        for i in range(self.per_window):
            index = self.offset + i + self.per_window * np.arange(len(self.starts))
            up = np.array(theta, dtype=np.float64)
            up[index] += step
            if central:
                down = np.array(theta, dtype=np.float64)
                down[index] -= step
                change = (residuals(up) - residuals(down)) / (2 * step)
            else:
                change = (residuals(up) - value) / step
            for w in range(len(self.starts)):
                column = i + self.per_window * w
                rows = np.nonzero(self.row_window == w + 1)[0]
                out[rows, column] = change[rows]
                prior_row = self.prior_start + column
                out[prior_row, column] = change[prior_row]
        return out
