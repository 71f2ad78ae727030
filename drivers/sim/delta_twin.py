"""Geometric twin of a linear Delta bench (the second mechanism, docs/mechanisms.md): true geometry, noisy joint
encoders, noisy end-effector observations.

What a camera looking down at a target on the plate's centre gives, after its frame has been registered to the
base frame: the plate's true centre with Gaussian noise, larger along the viewing axis (depth) than across it. The
true geometry differs from the nominal one by a few millimetres and milliradians. Seeded: the same seed gives the
same observations.

Two uses: :meth:`DeltaTwin.acquire` runs joint targets on the true mechanism without hardware (targets reached
exactly, encoders read with noise); :meth:`DeltaTwin.observe` gives the camera's observation of the true
mechanism at given true joint values (e.g. the simulated drives' actual positions, next to what the Modbus driver
read back), and :meth:`DeltaTwin.sim_mechanism` builds the simulated drives for a :class:`SimController`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.mechanisms.linear_delta import NOMINAL, LinearDelta, LinearDeltaParameters

from .mechanism import AxisConfig, Mechanism

Array = NDArray[np.float64]

#: The twin's default true geometry: nominal plus a few millimetres / milliradians.
DEFAULT_TRUTH = LinearDeltaParameters(
    R=(0.2021, 0.1987, 0.2009),
    theta=(NOMINAL.theta[0] + 0.004, NOMINAL.theta[1] - 0.003, NOMINAL.theta[2] + 0.0025),
    L=(0.3014, 0.2991, 0.3006),
    z0=(-0.4978, -0.5031, -0.5012),
    r=0.05,
)


@dataclass(frozen=True)
class DeltaNoise:
    """Standard deviations of the twin's observations (metres).

    Attributes
    ----------
    camera_m : tuple of 3 float
        Of the observed plate centre along base x, y, z (the camera looks down: z is its depth).
    encoder_m : float
        Of the joint encoders.
    """

    camera_m: tuple[float, float, float] = (1e-4, 1e-4, 2.5e-4)
    encoder_m: float = 1e-6


@dataclass
class DeltaTwin:
    """A linear Delta bench's truth and observations (seeded).

    Parameters
    ----------
    truth : LinearDeltaParameters
        The true geometry.
    noise : DeltaNoise
    seed : int
    """

    truth: LinearDeltaParameters = DEFAULT_TRUTH
    noise: DeltaNoise = field(default_factory=DeltaNoise)
    seed: int = 0
    mechanism: LinearDelta = field(default_factory=LinearDelta, init=False)
    rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def pose_true(self, q_true: ArrayLike) -> Array:
        """True plate centres at true joint values, shape (N, 3) or (3,), metres."""
        return self.mechanism.dkm(self.truth, q_true)

    def observe(self, q_true: ArrayLike) -> Array:
        """The camera's observation of the target at true joint values ``q_true`` (N, 3): the true end-effector
        point plus noise, shape (N, 3) or (3,), metres, base frame."""
        P = self.mechanism.ee_point(self.truth, self.pose_true(q_true))
        return P + self.rng.normal(0.0, 1.0, np.shape(P)) * np.asarray(self.noise.camera_m)

    def read_encoders(self, q_true: ArrayLike) -> Array:
        """Encoder readings of true joint values, metres (same shape)."""
        q = np.asarray(q_true, dtype=np.float64)
        return q + self.rng.normal(0.0, self.noise.encoder_m, q.shape)

    def acquire(self, q_targets: ArrayLike) -> dict[str, Array]:
        """Run joint targets on the true mechanism (each reached exactly) and observe.

        Parameters
        ----------
        q_targets : array_like, shape (N, 3)
            Joint targets, metres (from the nominal IKM, as a real bench computes them).

        Returns
        -------
        dict
            ``q`` (N, 3) encoder readings, ``points`` (N, 3) observed plate centres, ``points_std`` (3,),
            ``q_true`` (N, 3) and ``pose_true`` (N, 3); metres.
        """
        q_true = np.atleast_2d(np.asarray(q_targets, dtype=np.float64))
        return {
            "q": self.read_encoders(q_true),
            "points": self.observe(q_true),
            "points_std": np.asarray(self.noise.camera_m, dtype=np.float64),
            "q_true": q_true,
            "pose_true": self.pose_true(q_true),
        }

    def sim_mechanism(self, initial_pose: ArrayLike = (0.0, 0.0, -0.35), axis_config: AxisConfig | None = None) -> Any:
        """Simulated drives for this bench: a :class:`drivers.sim.mechanism.Mechanism` with three axes at the true
        IKM of ``initial_pose``, encoders quantised by the controller and noisy (``noise.encoder_m``), seeded.

        Its I4-specific parts (``pose_true``, the guided line) are not used for a Delta: observe with
        :meth:`observe` at :meth:`Mechanism.q_true`.
        """
        from .bench import fast_axis_config

        cfg = axis_config or fast_axis_config()
        cfg = AxisConfig(**{**cfg.__dict__, "encoder_noise_m": self.noise.encoder_m})
        q0 = self.mechanism.ikm(self.truth, initial_pose)
        return Mechanism(axis_config=cfg, initial_q=q0, seed=self.seed)


__all__ = ["DEFAULT_TRUTH", "DeltaNoise", "DeltaTwin"]
