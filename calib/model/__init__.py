"""The I4 model: kinematics, parameters, the mechanism seam and its mechanisms."""
