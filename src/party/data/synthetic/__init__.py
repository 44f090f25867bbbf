"""Procedural compositional motions in the HumanML3D layout (the embedded default dataset).

A motion is a legs action x an arms action x a root trajectory (or a sequence of two
such segments), built by forward kinematics over fixed bones, with captions, POS tags,
ground-truth part texts, mirrors and splits with held-out arm x leg combinations.
See docs/synthetic.md.
"""
from party.data.synthetic.arms import ARM_ACTIONS
from party.data.synthetic.body import build_body, forward_kinematics
from party.data.synthetic.captions import make_captions, make_part_texts
from party.data.synthetic.compose import mirror_joints, synthesize, synthesize_full
from party.data.synthetic.legs import LEG_ACTIONS
from party.data.synthetic.sampling import make_action, make_trajectory, sample_specs, single_spec
from party.data.synthetic.spec import ActionSpec, MotionSpec, Trajectory
from party.data.synthetic.writer import write_synthetic_dataset

__all__ = ["ARM_ACTIONS", "LEG_ACTIONS", "ActionSpec", "MotionSpec", "Trajectory", "build_body",
           "forward_kinematics", "make_action", "make_captions", "make_part_texts", "make_trajectory",
           "mirror_joints", "sample_specs", "single_spec", "synthesize", "synthesize_full",
           "write_synthetic_dataset"]
