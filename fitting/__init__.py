"""fitting: optimisation on top of dmarionette (JAX + optimistix): keyframe authoring, calibration.

This package may import ``dmarionette``; ``dmarionette`` never imports it. ``marionette_rollout``
exposes a checkpointed marionette rollout (``dmarionette.marionette_grad``) to JAX with a
custom VJP (docs/gradients.md).
"""

from .rollout import marionette_rollout as marionette_rollout
from .calibration_data import read_calibration_data as read_calibration_data
from .calibration_fit import calibrate_session as calibrate_session
