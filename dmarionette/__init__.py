"""dmarionette: a differentiable simulator of a string marionette (NVIDIA Warp).

The public API; everything else is implementation::

    import dmarionette as dm

    scene = dm.load_scene("hanging")                 # strings + puppet + bars
    model = dm.MarionetteModel(scene)
    solver = dm.SolverMarionette(model)
    a, b, control = model.state(), model.state(), model.control()
    solver.step(a, b, control)                       # one puppet step (n string steps)
    trajectory = dm.simulate_marionette(model, 2.0)  # many, without Python overhead
"""

from .control_bar import BarTrajectory as BarTrajectory
from .control_bar import ControlBar as ControlBar
from .export_bvh import export_bvh as export_bvh
from .export_common import read_marionette_trajectory as read_marionette_trajectory
from .export_gltf import export_gltf as export_gltf
from .marionette import MarionetteControl as MarionetteControl
from .marionette import MarionetteModel as MarionetteModel
from .marionette import MarionetteState as MarionetteState
from .marionette import SolverMarionette as SolverMarionette
from .marionette_rollout import MarionetteRollout as MarionetteRollout
from .marionette_rollout import MarionetteTrajectory as MarionetteTrajectory
from .marionette_rollout import simulate_marionette as simulate_marionette
from .scene import Scene as Scene
from .scene import builtin_scenes as builtin_scenes
from .scene import load_scene as load_scene
from .scene_fields import SceneError as SceneError
from .simulate import StringTrajectory as StringTrajectory
from .simulate import simulate_strings as simulate_strings
from .string_model import StringControl as StringControl
from .string_model import StringEffects as StringEffects
from .string_model import StringModel as StringModel
from .string_model import StringSpec as StringSpec
from .string_model import StringState as StringState
from .string_model import string_energy as string_energy
from .string_rollout import StringRollout as StringRollout
from .string_solver import SolverStringImplicit as SolverStringImplicit
from .trajectory_file import read_trajectory as read_trajectory
from .trajectory_file import write_trajectory as write_trajectory

__all__ = [
    "BarTrajectory",
    "ControlBar",
    "MarionetteControl",
    "MarionetteModel",
    "MarionetteRollout",
    "MarionetteState",
    "MarionetteTrajectory",
    "Scene",
    "SceneError",
    "SolverMarionette",
    "SolverStringImplicit",
    "StringControl",
    "StringEffects",
    "StringModel",
    "StringRollout",
    "StringSpec",
    "StringState",
    "StringTrajectory",
    "builtin_scenes",
    "export_bvh",
    "export_gltf",
    "load_scene",
    "read_marionette_trajectory",
    "read_trajectory",
    "simulate_marionette",
    "simulate_strings",
    "string_energy",
    "write_trajectory",
]
