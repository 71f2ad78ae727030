"""The legs method's constants: the a priori tolerance, the rod-pair floor, the step-3/4 equations' leg pairs."""

from __future__ import annotations

_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: Default std (m) of each of the seven parameters around the nominal geometry (:func:`calibrate_legs`'s prior): a
#: bench built to its drawings within about +/-10 mm per length (the simulator's truths lie within it)
PRIOR_STD_M = 0.01
#: The lock phases' joints' systematic error along their lines of sight (m, RMS per joint) for rods measured on images,
#: and the share of its variance common to a leg's two joints. The rods' shading biases a rod's limb edges by an amount
#: that depends on its apparent width, the same in every frame of a lock phase (the rod barely moves), so the frames
#: cannot average it and their scatter does not show it. Measured on the simulated bench's renders (docs/benchmarks.md).
JOINT_DEPTH_SYS_M = 0.8e-3
JOINT_DEPTH_SYS_LEG_SHARE = 0.5
#: Floor (m) of the rod-pair check's separation std: below any measurement (noise-free data are never flagged)
_PAIR_FLOOR_M = 1e-6
#: the four step-3/4 equations of a pose: (leg a, leg b) of |Ba Bb| - 2S, then of (Bb - Ba) . y - 2D
_EQ_LEGS = ((0, 1), (2, 3), (0, 2), (1, 3))
