"""Multi-head camera rigs (CONTRACT section 3, "Rig sessions"): the manifest, the rig's data,
the pose algebra of heads on one mount, and the adjustment of every head together."""

from fieldcal.rig.adjustment import RigOptions, RigResult, adjust_rig
from fieldcal.rig.data import RigData, RigHead
from fieldcal.rig.session import RigSession, load_rig_session, rig_data_from_observations

__all__ = ["RigData", "RigHead", "RigOptions", "RigResult", "RigSession", "adjust_rig",
           "load_rig_session", "rig_data_from_observations"]
