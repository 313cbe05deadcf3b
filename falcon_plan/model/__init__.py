"""The Falcon model: parameters, kinematics, workspace and rigid-body dynamics."""
from falcon_plan.model.params import ACRA2009, LIBNIFALCON, FalconParams, get_params

__all__ = ["ACRA2009", "LIBNIFALCON", "FalconParams", "get_params"]
