"""The methods' public measurement models through the registry, their settings objects, and what the legs method takes
from the combined fit (passed in, not recomputed)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.formats.plan import make_plan
from calib.identify.combined import CombinedSettings, calibrate_combined, model_ratios
from calib.identify.combined_measurements import CombinedMeasurements
from calib.identify.end_effector import EndEffectorSettings, calibrate_end_effector
from calib.identify.legs import LegsSettings, calibrate_legs
from calib.identify.pose_set_model import PoseSetModel
from calib.identify.registry import MethodSpec, method_identifiability, method_model
from calib.model.parameters import COMBINATION_NAMES, NOMINAL
from calib.numerics.numdiff import central_jacobian


def _q() -> np.ndarray:
    return np.array([s.q for s in make_plan("pose-set", NOMINAL, seed=3).steps])


def test_the_combined_models_covariance_is_the_inverse_information_in_the_four_combinations():
    """The combined model's measurements depend on the seven parameters through the four combinations only: its
    covariance of the combinations is (J4^T J4)^-1 sigma^2, J4 the Jacobian in the combinations (model_ratios)."""
    q = _q()
    sigma = 2e-3
    model = method_model("combined", NOMINAL, q)
    assert isinstance(model, PoseSetModel) and model.n_nuisance == 0
    xi0 = np.array([NOMINAL.combinations()[k] for k in COMBINATION_NAMES])
    np.testing.assert_allclose(model.predict(), model_ratios(xi0, q).ravel(), rtol=1e-12, atol=1e-15)
    J4 = central_jacobian(lambda xi: model_ratios(xi, q).ravel(), xi0, 1e-6)
    expected = sigma**2 * np.linalg.inv(J4.T @ J4)
    np.testing.assert_allclose(model.covariance(sigma), expected, rtol=1e-5)
    assert model.jacobian().shape == (q.shape[0] * 8, 7)
    np.testing.assert_allclose(model.residuals(model.predict()), 0.0, atol=0.0)


@pytest.mark.parametrize("name, n_nuisance", [("end-effector", 12), ("legs", 6)])
def test_every_builtin_method_has_a_model_the_identifiability_report_reads(name, n_nuisance):
    q = _q()
    model = method_model(name, NOMINAL, q)
    assert model.n_nuisance == n_nuisance
    cov = model.covariance(1e-4)
    assert cov.shape == (4, 4) and np.all(np.linalg.eigvalsh(cov) > 0)
    # the report analyses the same model: its singular values are those of the model's Jacobian, nuisances out
    J = model.jacobian()
    Q, _ = np.linalg.qr(J[:, 7:])
    J7 = J[:, :7] - Q @ (Q.T @ J[:, :7])
    s = np.linalg.svd(J7, compute_uv=False)
    np.testing.assert_allclose(method_identifiability(name, NOMINAL, q)["singular_values"], s, rtol=1e-12)


def test_a_method_spec_has_its_model_in_both_forms():
    def fit(obs, ctx):  # pragma: no cover - never called
        raise AssertionError

    def f_of(params, q):
        return (lambda v: np.concatenate([v[:7], v[7:] * 2.0]), 2)

    from_tuple = MethodSpec(name="toy-a", label="a", colour="#000000", description="d", fit=fit, identifiability=f_of)
    assert from_tuple.model is not None
    m = from_tuple.model(NOMINAL, _q())
    assert m.n_nuisance == 2 and m.predict().tolist() == [*NOMINAL.vector(), 0.0, 0.0]

    def model_of(params, q):
        return PoseSetModel(lambda v: v * 3.0, params, 1)

    from_model = MethodSpec(name="toy-b", label="b", colour="#000000", description="d", fit=fit, model=model_of)
    assert from_model.identifiability is not None
    f, k = from_model.identifiability(NOMINAL, _q())
    assert k == 1 and f(np.ones(8)).tolist() == [3.0] * 8
    assert from_model.summary()["identifiability"]


def test_settings_objects_give_the_keyword_arguments_results(noise_free_obs):
    obs, _ = noise_free_obs
    a = calibrate_combined(obs, weighting="frobenius")
    b = calibrate_combined(obs, settings=CombinedSettings(weighting="frobenius"))
    assert a.to_dict() == b.to_dict()
    a = calibrate_end_effector(obs, iterations=1)
    b = calibrate_end_effector(obs, settings=EndEffectorSettings(iterations=1))
    assert a.to_dict() == b.to_dict()
    a = calibrate_legs(obs, prior_std_m=None)
    b = calibrate_legs(obs, settings=LegsSettings(prior_std_m=None))
    assert a.to_dict() == b.to_dict()


def test_the_legs_method_takes_the_combined_measurements_passed_in(noise_free_obs, monkeypatch):
    """Given the combined fit's measurements, the legs method runs no combined fit of its own (on observations whose
    rods carry no limb samples it never needs one)."""
    import calib.identify.combined as combined

    obs, _ = noise_free_obs
    alone = calibrate_legs(obs)

    def no_fit(*args, **kwargs):
        raise AssertionError("the combined fit ran again")

    monkeypatch.setattr(combined, "calibrate_combined", no_fit)
    given = calibrate_legs(obs, combined=CombinedMeasurements())
    assert given.to_dict() == alone.to_dict()
