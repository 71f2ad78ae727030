"""A method's measurement model at a set of poses, in the manner of scipy.optimize: what it predicts, its residuals,
their Jacobian and the covariance of the estimate.

Every method exposes one (``pose_set_model(params, q)`` in its module, registered as :attr:`MethodSpec.model
<calib.identify.registry.MethodSpec.model>`): the quantities it measures at the encoder values ``q`` as a function of
the seven parameters (:data:`calib.model.parameters.PARAMETER_NAMES` order) followed by the method's nuisance unknowns
(camera and board placements). The identifiability report (:func:`calib.identify.identifiability.analyse` of its
``fun``) and
experiment design read it through the registry (:func:`calib.identify.registry.method_model`), whatever the method.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calib.model.parameters import SEVEN_TO_FOUR, I4Parameters
from calib.numerics.numdiff import central_jacobian

#: step of the numerical Jacobian (m for the parameters, the nuisance's own units)
JACOBIAN_STEP = 1e-6


@dataclass(frozen=True)
class PoseSetModel:
    """A method's measurement model at a set of poses.

    Attributes
    ----------
    fun : callable
        ``fun(x) -> (M,)``: the predicted measurements for the unknowns ``x`` (7 + n_nuisance,): the seven parameters
        (m), then the nuisance unknowns (rad, m).
    params : I4Parameters
        The linearisation point (its seven parameters are ``x0``'s first seven; ``T_per_rad`` held).
    n_nuisance : int
        Nuisance unknowns after the seven (their start is zero).
    """

    fun: Callable[[np.ndarray], np.ndarray]
    params: I4Parameters
    n_nuisance: int = 0

    @property
    def x0(self) -> np.ndarray:
        """The unknowns at the linearisation point, shape (7 + n_nuisance,)."""
        return np.concatenate([np.asarray(self.params.vector()), np.zeros(self.n_nuisance)])

    def predict(self, x: np.ndarray | None = None) -> np.ndarray:
        """The predicted measurements (M,) for ``x`` (default :attr:`x0`).

        Parameters
        ----------
        x : ndarray, shape (7 + n_nuisance,), optional
            The seven parameters (m) then the nuisance unknowns.

        Returns
        -------
        ndarray, shape (M,)
            The measurements, in their units.
        """
        return self.fun(self.x0 if x is None else np.asarray(x, dtype=np.float64))

    def residuals(self, measured: np.ndarray, x: np.ndarray | None = None) -> np.ndarray:
        """Prediction minus ``measured`` (M,), in the measurements' units.

        Parameters
        ----------
        measured : ndarray, shape (M,)
            The measurements (any shape that flattens to (M,)).
        x : ndarray, shape (7 + n_nuisance,), optional
            The seven parameters (m) then the nuisance unknowns (default :attr:`x0`).

        Returns
        -------
        ndarray, shape (M,)
            The residuals.
        """
        return self.predict(x) - np.asarray(measured, dtype=np.float64).ravel()

    def jacobian(self, x: np.ndarray | None = None, h: float = JACOBIAN_STEP) -> np.ndarray:
        """d prediction / d unknowns, shape (M, 7 + n_nuisance), by central differences of step ``h``.

        Parameters
        ----------
        x : ndarray, shape (7 + n_nuisance,), optional
            The seven parameters (m) then the nuisance unknowns (default :attr:`x0`).
        h : float
            The central differences' step, in the unknowns' units.

        Returns
        -------
        ndarray, shape (M, 7 + n_nuisance)
            The Jacobian (measurement units per m, or per nuisance unit).
        """
        return central_jacobian(self.fun, self.x0 if x is None else np.asarray(x, dtype=np.float64), h)

    def covariance(self, noise_std: float = 1.0, x: np.ndarray | None = None) -> np.ndarray:
        """Covariance (4, 4) of the four identifiable combinations (:data:`calib.model.parameters.COMBINATION_NAMES`),
        m^2,
        for independent measurement noise of std ``noise_std`` (the measurements' units): the nuisance unknowns
        projected out, ``noise_std^2 A (J^T J)^+ A^T`` with ``A`` = :data:`calib.model.parameters.SEVEN_TO_FOUR` (the
        combinations are estimable whenever the pose set identifies them).

        Parameters
        ----------
        noise_std : float
            The measurements' noise std, in their units.
        x : ndarray, shape (7 + n_nuisance,), optional
            The linearisation point (default :attr:`x0`).

        Returns
        -------
        ndarray, shape (4, 4)
            The combinations' covariance, m^2.
        """
        J = self.jacobian(x)
        J7 = J[:, :7]
        if self.n_nuisance:
            Q, _ = np.linalg.qr(J[:, 7:])
            J7 = J7 - Q @ (Q.T @ J7)
        return noise_std**2 * SEVEN_TO_FOUR @ np.linalg.pinv(J7.T @ J7) @ SEVEN_TO_FOUR.T


#: ``model(params, q) -> PoseSetModel``: a method's model at encoder values ``q`` (N, 4), m.
ModelFactory = Callable[[I4Parameters, np.ndarray], PoseSetModel]

__all__ = ["JACOBIAN_STEP", "ModelFactory", "PoseSetModel"]
