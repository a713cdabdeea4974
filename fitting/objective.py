"""The authoring objective: keyframe error, smoothness, device workspace, device force.

All terms are weighted residuals ``r`` (``loss = 0.5 * sum(r^2)``), so the same pieces
drive a scalar minimiser (BFGS on the loss, reverse-mode gradient) and a least-squares
solver (Gauss-Newton / Levenberg-Marquardt on the residual vector). With weights ``w``
from the keyframes file (``[weights]``, :class:`fitting.keyframes.Weights`):

- **keyframes**: ``w_point (x - x*)`` for every targeted point or body centre [m],
  ``w_joint (q - q*)`` for every targeted joint angle [rad] and ``w_joint`` times the
  rotation vector of every targeted body orientation's error [rad], at the puppet step
  nearest each keyframe time;
- **smoothness**: ``w_smoothness`` times the authored bars' accelerations, so that
  ``0.5 sum r^2 = 0.5 w^2 \\int (|a|^2 + |alpha|^2) dt`` (exact for the Hermite spline;
  positions in m/s^2, angles in rad/s^2);
- **workspace**: ``w_workspace sqrt(dt)`` times how far each authored bar's centre is
  outside the device workspace box, per axis and string step. The box is the device's
  (``[author] device``: a PHANToM Omni's 160 x 120 x 70 mm by default), scaled by
  ``workspace_scale`` and placed with the device origin at the bar's start, as
  ``dmarionette live`` maps it (``P' = S W P``);
- **force**: ``w_force sqrt(dt)`` times how far the force the device would be sent,
  ``force_scale |F|`` (``F`` the strings' exact reaction on the bar, or eq. 4), exceeds
  the device's peak force, per string step.

The workspace and force terms are one-sided (zero inside the limits) and quadratic
outside, so the loss stays C1.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dmarionette.rotations import euler_to_matrix, matrix_to_quat

from .bar_spline import BarParameterisation
from .keyframes import AuthorSpec, keyframe_steps

jax.config.update("jax_enable_x64", True)

__all__ = ["AuthoringObjective", "device_limits"]


def device_limits(spec: AuthorSpec) -> dict | None:
    """The device's workspace box (device frame) [m] and peak force [N], or None for ``none``."""
    if spec.device == "none":
        return None
    if spec.device == "omni":
        from dmarionette.hw.simulated import DEFAULT_SIMULATED_SPEC as device
    else:
        from dmarionette.hw.falcon import HapticDeviceFalcon

        device = HapticDeviceFalcon().spec  # the spec is known without opening the device
    return {"name": device.name, "workspace_min": np.asarray(device.workspace_min, float),
            "workspace_max": np.asarray(device.workspace_max, float),
            "max_force": float(spec.max_force if spec.max_force is not None else device.max_force)}


class AuthoringObjective:
    """Residuals and loss of a keyframes problem, as functions ``fn(y, args)`` of the knots.

    Args:
        spec: the keyframes file.
        model: the marionette built from ``spec.scene``.
        parameterisation: the authored bars' knots -> rollout inputs.
        rollout: ``dict of jax arrays -> dict of jax arrays``, the differentiable rollout
            (``fitting.rollout.marionette_rollout(engine)``).
        constants: the rollout's other inputs (string constants, initial state), fixed.
    """

    def __init__(self, spec: AuthorSpec, model, parameterisation: BarParameterisation,
                 rollout: Callable[[dict], dict], constants: dict[str, np.ndarray]):
        self.spec = spec
        self.param = parameterisation
        self.rollout = rollout
        self.constants = {k: jnp.asarray(v) for k, v in constants.items()}
        self.steps = keyframe_steps(spec, model.puppet_dt)
        self.puppet_dt = float(model.puppet_dt)
        puppet = model.puppet
        joint_offset, offset = {}, 7  # the free root: position, quaternion
        for joint in spec.scene.puppet.joints:
            count = 4 if joint.type == "ball" else len(joint.axes)
            joint_offset[joint.name] = offset
            offset += count
        rows = {"point": [], "body": [], "joint": [], "orientation": []}
        cols = {"point": [], "body": [], "joint": [], "orientation": []}
        targets = {"point": [], "body": [], "joint": [], "orientation": []}
        for k, pose in enumerate(spec.keyframes):
            for name, value in pose.points.items():
                rows["point"].append(self.steps[k]), cols["point"].append(puppet.point_names.index(name))
                targets["point"].append(value)
            for name, value in pose.bodies.items():
                rows["body"].append(self.steps[k]), cols["body"].append(puppet.body_names.index(name))
                targets["body"].append(value)
            for name, angles in pose.joints.items():
                for axis, angle in enumerate(angles):
                    rows["joint"].append(self.steps[k]), cols["joint"].append(joint_offset[name] + axis)
                    targets["joint"].append(np.radians(angle))
        for k, pose in enumerate(spec.keyframes):
            for name, angles in pose.orientations.items():
                rows["orientation"].append(self.steps[k]), cols["orientation"].append(puppet.body_names.index(name))
                targets["orientation"].append(matrix_to_quat(euler_to_matrix(np.asarray(angles, float))))
        self.rows = {k: np.array(v, dtype=np.int64) for k, v in rows.items()}
        self.cols = {k: np.array(v, dtype=np.int64) for k, v in cols.items()}
        self.targets = {"point": np.array(targets["point"], float).reshape(-1, 3),
                        "body": np.array(targets["body"], float).reshape(-1, 3),
                        "joint": np.array(targets["joint"], float),
                        "orientation": np.array(targets["orientation"], float).reshape(-1, 4)}
        self.limits = device_limits(spec)
        self.feedback_output = "bar_reaction" if spec.feedback == "reaction" else "bar_feedback"
        self.boxes = {}
        if self.limits is not None:
            for a in parameterisation.authored:
                start = a["initial"][0, :3]
                self.boxes[a["name"]] = (start + spec.workspace_scale * self.limits["workspace_min"],
                                         start + spec.workspace_scale * self.limits["workspace_max"])

    # ----------------------------------------------------------------- pieces
    def outputs(self, y) -> dict[str, jnp.ndarray]:
        """The rollout's outputs for knots ``y``."""
        return self.rollout({**self.constants, **self.param.rollout_inputs(y)})

    def keyframe_residuals(self, outputs: dict) -> dict[str, jnp.ndarray]:
        """Unweighted keyframe errors: points and bodies [m] ``(N, 3)``, joints [rad] ``(N,)``,
        orientations ``(N, 3)``: ``2 sign(w) v`` of ``q_target^-1 q`` [rad] (the rotation
        vector of the error, to second order; its length is ``2 sin(angle / 2)``).
        NumPy in, NumPy out; JAX in, JAX out."""
        r = self.rows, self.cols, self.targets
        xp = np if isinstance(outputs["body_rot"], np.ndarray) else jnp
        q = outputs["body_rot"][r[0]["orientation"], r[1]["orientation"]]
        t = r[2]["orientation"]
        tv, tw, qv, qw = -t[:, :3], t[:, 3:], q[:, :3], q[:, 3:]  # conj(target) * q, (x, y, z, w)
        v = tw * qv + qw * tv + xp.cross(tv, qv)
        w = tw * qw - xp.sum(tv * qv, axis=1, keepdims=True)
        return {
            "point": outputs["point_pos"][r[0]["point"], r[1]["point"]] - r[2]["point"],
            "body": outputs["body_pos"][r[0]["body"], r[1]["body"]] - r[2]["body"],
            "joint": outputs["joint_q"][r[0]["joint"], r[1]["joint"]] - r[2]["joint"],
            "orientation": 2.0 * xp.where(w < 0.0, -1.0, 1.0) * v,
        }

    def residuals(self, y, args=None) -> dict[str, jnp.ndarray]:
        """All weighted residuals, by term (``keyframes``, ``smoothness``, ``workspace``, ``force``)."""
        return self.residuals_of(y, self.outputs(y))

    def residuals_of(self, y, outputs: dict) -> dict[str, jnp.ndarray]:
        """:meth:`residuals` from the rollout's ``outputs`` at ``y`` (no rollout)."""
        w = self.spec.weights
        key = self.keyframe_residuals(outputs)
        terms = {"keyframes": jnp.concatenate([w.point * key["point"].ravel(), w.point * key["body"].ravel(),
                                               w.joint * key["joint"], w.joint * key["orientation"].ravel()]),
                 "smoothness": w.smoothness * self.param.acceleration_residuals(y)}
        if self.spec.end_at_rest:
            terms["rest"] = w.rest * self.end_velocity(outputs).ravel()
        if self.limits is not None:
            root_dt = np.sqrt(self.param.string_dt)
            paths = self.param.bar_paths(y)
            outside, excess = [], []
            for a in self.param.authored:
                lo, hi = self.boxes[a["name"]]
                position = paths[a["name"]][0]
                outside.append((jax.nn.relu(position - hi) + jax.nn.relu(lo - position)).ravel())
                force = outputs[self.feedback_output][:, a["index"]]
                magnitude = self.spec.force_scale * jnp.sqrt(jnp.sum(force**2, axis=-1) + 1e-12)
                excess.append(jax.nn.relu(magnitude - self.limits["max_force"]))
            terms["workspace"] = w.workspace * root_dt * jnp.concatenate(outside)
            terms["force"] = w.force * root_dt * jnp.concatenate(excess)
        return terms

    def end_velocity(self, outputs: dict):
        """Every body centre's mean velocity over the last puppet step [m/s], ``(B, 3)``."""
        body = outputs["body_pos"]
        return (body[-1] - body[-2]) / self.puppet_dt

    # ----------------------------------------------------------------- solver functions
    def loss(self, y, args=None):
        """``0.5 * sum(r^2)`` over every term (the scalar BFGS minimises)."""
        return 0.5 * sum(jnp.sum(r**2) for r in self.residuals(y).values())

    def loss_terms(self, y, args=None):
        """``(loss, {term: 0.5 sum r^2})``: the loss with the terms as aux."""
        terms = {k: 0.5 * jnp.sum(r**2) for k, r in self.residuals(y).items()}
        return sum(terms.values()), terms

    def loss_terms_of(self, y, outputs: dict) -> tuple[float, dict[str, float]]:
        """:meth:`loss_terms` from the rollout's ``outputs`` at ``y`` (jitted, NumPy out)."""
        if not hasattr(self, "_terms_of"):
            self._terms_of = jax.jit(lambda y, o: {k: 0.5 * jnp.sum(r**2) for k, r in self.residuals_of(y, o).items()})
        terms = {k: float(v) for k, v in self._terms_of(y, {k: jnp.asarray(v) for k, v in outputs.items()}).items()}
        return sum(terms.values()), terms

    def residual_vector(self, y, args=None):
        """Every weighted residual in one vector (what Gauss-Newton / LM fit)."""
        return jnp.concatenate([r.ravel() for r in self.residuals(y).values()])

    # ----------------------------------------------------------------- reports
    def limits_report(self, y, outputs: dict) -> dict:
        """Per authored bar: the largest device force ``force_scale |F|`` [N] and the largest
        distance outside the workspace box [m] over the motion (NumPy)."""
        report = {}
        if not hasattr(self, "_bar_paths"):
            self._bar_paths = jax.jit(self.param.bar_paths)
        paths = self._bar_paths(y)
        for a in self.param.authored:
            force = np.asarray(outputs[self.feedback_output])[:, a["index"]]
            entry = {"max_device_force_N": float(self.spec.force_scale * np.linalg.norm(force, axis=-1).max())}
            if self.limits is not None:
                lo, hi = self.boxes[a["name"]]
                position = np.asarray(paths[a["name"]][0])
                outside = np.maximum(position - hi, 0.0) + np.maximum(lo - position, 0.0)
                entry["max_outside_workspace_m"] = float(outside.max())
                entry["max_force_N"] = self.limits["max_force"]
            report[a["name"]] = entry
        return report

    def keyframe_report(self, outputs: dict) -> list[dict]:
        """Per keyframe: its time, the step time used, and errors per target (NumPy)."""
        key = {k: np.asarray(v) for k, v in self.keyframe_residuals(outputs).items()}
        puppet_dt = self.param.string_dt * round(self.spec.scene.string_hz / self.spec.scene.puppet_hz)
        report, counts = [], {"point": 0, "body": 0, "joint": 0, "orientation": 0}
        for k, pose in enumerate(self.spec.keyframes):
            entry = {"t": pose.t, "t_step": float(self.steps[k] * puppet_dt), "points_m": {}, "bodies_m": {},
                     "joints_deg": {}, "orientations_deg": {}}
            for name in pose.points:
                entry["points_m"][name] = float(np.linalg.norm(key["point"][counts["point"]]))
                counts["point"] += 1
            for name in pose.bodies:
                entry["bodies_m"][name] = float(np.linalg.norm(key["body"][counts["body"]]))
                counts["body"] += 1
            for name, angles in pose.joints.items():
                n = len(angles)
                entry["joints_deg"][name] = np.degrees(key["joint"][counts["joint"]:counts["joint"] + n]).tolist()
                counts["joint"] += n
            for name in pose.orientations:
                half = min(float(np.linalg.norm(key["orientation"][counts["orientation"]])) / 2.0, 1.0)
                entry["orientations_deg"][name] = float(np.degrees(2.0 * np.arcsin(half)))
                counts["orientation"] += 1
            positions = list(entry["points_m"].values()) + list(entry["bodies_m"].values())
            entry["max_position_error_m"] = max(positions) if positions else 0.0
            angles = [abs(a) for v in entry["joints_deg"].values() for a in v]
            entry["max_joint_error_deg"] = max(angles) if angles else 0.0
            entry["max_orientation_error_deg"] = max(entry["orientations_deg"].values(), default=0.0)
            report.append(entry)
        return report
