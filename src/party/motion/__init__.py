"""Motion representation: skeletons, HumanML3D features, body-part layouts."""
from party.motion.skeleton import Skeleton, get_skeleton
from party.motion.features import joints_to_features, recover_from_ric, recover_from_ric_np
from party.motion.parts import PartLayout

__all__ = ["Skeleton", "get_skeleton", "joints_to_features", "recover_from_ric",
           "recover_from_ric_np", "PartLayout"]
