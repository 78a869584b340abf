"""Simulated Model-T42 hands (MuJoCo): variants, the step interface, random and sustained-action collection.

No ROS and no torch here.
"""

from t42_transfer.hand.params import HandParams, variant
from t42_transfer.hand.sim import GraspFailed, SimulatedHand

__all__ = ["GraspFailed", "HandParams", "SimulatedHand", "variant"]
