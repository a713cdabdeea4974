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

from .scene.bars import BarTrajectory as BarTrajectory
from .scene.bars import ControlBar as ControlBar
from .io.export.bvh import export_bvh as export_bvh
from .io.export.common import read_marionette_trajectory as read_marionette_trajectory
from .io.export.gltf import export_gltf as export_gltf
from .grad.engine import MarionetteGradient as MarionetteGradient
from .marionette.solver import MarionetteControl as MarionetteControl
from .marionette.solver import MarionetteModel as MarionetteModel
from .marionette.solver import MarionetteState as MarionetteState
from .marionette.solver import SolverMarionette as SolverMarionette
from .marionette.rollout import MarionetteRollout as MarionetteRollout
from .marionette.rollout import MarionetteTrajectory as MarionetteTrajectory
from .marionette.rollout import simulate_marionette as simulate_marionette
from .marionette.rollout import simulate_worlds as simulate_worlds
from .scene.scene import Scene as Scene
from .scene.scene import builtin_scenes as builtin_scenes
from .scene.scene import load_scene as load_scene
from .scene.fields import SceneError as SceneError
from .strings.simulate import StringTrajectory as StringTrajectory
from .strings.simulate import simulate_strings as simulate_strings
from .strings.model import StringControl as StringControl
from .strings.model import StringEffects as StringEffects
from .strings.model import StringModel as StringModel
from .strings.model import StringSpec as StringSpec
from .strings.model import StringState as StringState
from .strings.model import string_energy as string_energy
from .strings.rollout import StringRollout as StringRollout
from .strings.solver import SolverStringImplicit as SolverStringImplicit
from .io.trajectory import read_trajectory as read_trajectory
from .io.trajectory import write_trajectory as write_trajectory

__all__ = [
    "BarTrajectory",
    "ControlBar",
    "MarionetteGradient",
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
    "simulate_worlds",
    "simulate_strings",
    "string_energy",
    "write_trajectory",
]
