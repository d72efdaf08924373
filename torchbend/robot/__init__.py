r"""Layer 6, robot-driven cloth: pins bound to link frames and capsule colliders on links, through
the batched, differentiable forward kinematics of pytorch-kinematics (URDF).

* :class:`Robot` loads a URDF (a file, an XML string, or the name of an asset shipped in
  ``torchbend/robot/assets``, e.g. ``"folding_arm.urdf"``) in float64 and evaluates link transforms
  for joint vectors ``q (..., J)``.
* :class:`LinkPins` binds cloth vertices to links; :class:`LinkCapsule` is a capsule fixed in a
  link's frame; :class:`RobotScene` ties a :class:`~torchbend.ClothModel` to a robot (implicit-Euler
  steps, and a static solve differentiable in the joint angles by the implicit adjoint).
"""
from .scene import LinkCapsule, LinkPins, RobotScene, trajectory
from .urdf import Robot, asset_path

__all__ = ["LinkCapsule", "LinkPins", "Robot", "RobotScene", "asset_path", "trajectory"]
