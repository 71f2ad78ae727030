"""A toy identification method for tests/test_method_registry.py: "a-priori" returns the nominal parameters with
their manufacturing tolerance as standard deviation (no fit). Importing this module registers it, in any process
(the service's fit processes import it through :func:`calib.identify.registry.plugin_modules`, a CLI process through
``I4CAL_METHODS=tests._toy_method``)."""

from __future__ import annotations

import numpy as np

from calib.formats.observations import Observations
from calib.identify.registry import MethodContext, MethodSpec, register_method
from calib.identify.result import MethodResult, std_dict
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES

#: Manufacturing tolerance of each of the seven parameters (one standard deviation), metres.
TOLERANCE_M = 5e-3

#: The combinations as a linear map of the seven parameters (rows: COMBINATION_NAMES, columns: PARAMETER_NAMES).
_A = np.zeros((4, 7))
for _row, _terms in enumerate(
    ({"L": 1.0}, {"H": 1.0, "D": -1.0}, {"S": 1.0, "q02": -0.5}, {"S": 1.0, "q04": -0.5, "q03": 0.5})
):
    for _name, _c in _terms.items():
        _A[_row, PARAMETER_NAMES.index(_name)] = _c


def fit_a_priori(obs: Observations, ctx: MethodContext) -> MethodResult:
    nominal = obs.nominal
    cov = TOLERANCE_M**2 * _A @ _A.T
    combos = nominal.combinations()
    return MethodResult(
        method="a-priori",
        combinations={k: float(combos[k]) for k in COMBINATION_NAMES},
        combinations_std=std_dict(cov),
        covariance=cov,
        residual_rms=0.0,
        residual_unit="m",
        n_observations=0,
        n_poses=len(obs.arrays("poses")),
        iterations=0,
        converged=True,
        message="no fit: the nominal parameters with their tolerance",
        parameters={k: float(getattr(nominal, k)) for k in PARAMETER_NAMES},
        parameters_std=dict.fromkeys(PARAMETER_NAMES, TOLERANCE_M),
    )


SPEC = register_method(
    MethodSpec(
        name="a-priori",
        label="A priori (toy, no fit)",
        colour="#8c564b",
        description="the nominal parameters with their manufacturing tolerance as standard deviation",
        fit=fit_a_priori,
        required_phases=("poses",),
    ),
    replace=True,
)
