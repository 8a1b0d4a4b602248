"""Pure numpy kinematics, one module per concept (import them by name: ``from labcal.kinematics import se3``):
:mod:`~labcal.kinematics.se3` (SE(3) tools), :mod:`~labcal.kinematics.poe` (the local POE model and its
definition), :mod:`~labcal.kinematics.conversions` (DH/MDH/URDF conversions) and :mod:`~labcal.kinematics.metric`
(the length-scaled metric)."""
