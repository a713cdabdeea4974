"""fitting: optimisation on top of dmarionette (JAX + optimistix): keyframe authoring, calibration.

This package may import ``dmarionette``; ``dmarionette`` never imports it. ``marionette_rollout``
exposes a checkpointed marionette rollout (``dmarionette.grad.engine``) to JAX with a
custom VJP, ``marionette_rollout_jvp`` the same rollout with a custom JVP (forward mode)
(docs/gradients.md).
"""

# Keyframe authoring (docs/authoring.md).
from .author import AuthoringProblem as AuthoringProblem
from .author import author as author
from .author import build_problem as build_problem
from .author import enable_compilation_cache as enable_compilation_cache
from .author_solve import EXIT_CODES as EXIT_CODES
from .author_solve import solve_keyframes as solve_keyframes
from .bar_spline import BarParameterisation as BarParameterisation
from .keyframes import AuthorSpec as AuthorSpec
from .keyframes import KeyframeError as KeyframeError
from .keyframes import keyframes_from_table as keyframes_from_table
from .keyframes import load_keyframes as load_keyframes
from .objective import AuthoringObjective as AuthoringObjective
from .rollout import marionette_rollout as marionette_rollout
from .rollout import marionette_rollout_jvp as marionette_rollout_jvp
from .solve import solve as solve

# Calibration (docs/calibration.md).
from .calibration_data import read_calibration_data as read_calibration_data
from .calibration_fit import calibrate_session as calibrate_session

__all__ = ["AuthorSpec", "AuthoringObjective", "AuthoringProblem", "BarParameterisation", "EXIT_CODES",
           "KeyframeError", "author", "build_problem", "enable_compilation_cache", "solve_keyframes", "calibrate_session", "keyframes_from_table", "load_keyframes",
           "marionette_rollout", "marionette_rollout_jvp", "read_calibration_data", "solve"]
