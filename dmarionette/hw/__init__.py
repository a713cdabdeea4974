"""Haptic devices, device-to-world mapping and the 1 kHz servo loop.

Devices read poses and write forces, nothing else: this package imports neither the
simulator's kernels nor Warp. Hardware back-ends import their driver libraries (ctypes
``libHD``, ``usb``, ``hid``) only when a device is opened.

    from dmarionette.hw import HapticDeviceSimulated, ServoLoop

    device = HapticDeviceSimulated(lambda t: [0.02 * t, 0.0, 0.0])
    stats = ServoLoop(device, lambda sample, t: -100.0 * sample.position).run(duration=1.0)
    print(stats.summary())
"""

from .device import AbstractHapticDevice as AbstractHapticDevice
from .device import DeviceDisconnectedError as DeviceDisconnectedError
from .device import HapticDeviceError as HapticDeviceError
from .device import HapticDeviceSpec as HapticDeviceSpec
from .device import HapticSample as HapticSample
from .falcon import HapticDeviceFalcon as HapticDeviceFalcon
from .falcon_kinematics import FalconGeometry as FalconGeometry
from .falcon_kinematics import FalconKinematics as FalconKinematics
from .mapping import DeviceMapping as DeviceMapping
from .mapping import rigid_transform as rigid_transform
from .mapping import scale_transform as scale_transform
from .openhaptics import HapticDeviceOpenHaptics as HapticDeviceOpenHaptics
from .safety import ForceSafetyFilter as ForceSafetyFilter
from .safety import SafetyConfig as SafetyConfig
from .safety import clamp_force as clamp_force
from .servo import PhysicsLink as PhysicsLink
from .servo import PhysicsStep as PhysicsStep
from .servo import ServoLoop as ServoLoop
from .servo import ServoStatistics as ServoStatistics
from .servo import run_servo_loop as run_servo_loop
from .shm_link import PhysicsProcessError as PhysicsProcessError
from .shm_link import SharedMemoryPhysics as SharedMemoryPhysics
from .simulated import HapticDeviceReplay as HapticDeviceReplay
from .simulated import HapticDeviceSimulated as HapticDeviceSimulated
from .spacemouse import HapticDeviceSpaceMouse as HapticDeviceSpaceMouse

__all__ = [
    "AbstractHapticDevice",
    "DeviceDisconnectedError",
    "DeviceMapping",
    "FalconGeometry",
    "FalconKinematics",
    "ForceSafetyFilter",
    "HapticDeviceError",
    "HapticDeviceFalcon",
    "HapticDeviceOpenHaptics",
    "HapticDeviceReplay",
    "HapticDeviceSimulated",
    "HapticDeviceSpaceMouse",
    "HapticDeviceSpec",
    "HapticSample",
    "PhysicsLink",
    "PhysicsProcessError",
    "PhysicsStep",
    "SafetyConfig",
    "ServoLoop",
    "ServoStatistics",
    "SharedMemoryPhysics",
    "clamp_force",
    "rigid_transform",
    "run_servo_loop",
    "scale_transform",
]
