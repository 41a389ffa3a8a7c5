"""When the in-flight estimate is applied (issue 9): a stored estimate that had not passed the test for being
applied is not applied from the first sample of the next run, and no correction is applied while its heading
uncertainty is beyond the linearisation (however large the heading change it would make)."""

from __future__ import annotations

import math

import numpy as np

from magcomp.adapters.config import InflightConfig
from magcomp.core.inflight import N_SOFT, N_SYM
from magcomp.core.inflight.apply import MAX_APPLY_HEADING_SIGMA_DEG
from magcomp.service.inflight_stage import InflightStage

NORM = 500.0  # mgauss; at the default 60 deg of inclination the horizontal field is half of it
FIELD = (100.0, 0.0, 400.0)
D_MEAN = [300.0, -200.0, 0.0]  # moves the horizontal field from (100, 0) to (-200, 200): 135 deg


def _stage(d_sd: float, applied: bool | None) -> InflightStage:
    # relative form: [soft iron E (N_SOFT), d (3), theta (3)]; no soft iron, so that L = I
    warm: dict[str, object] = {
        "form": "relative",
        "n_motors": 0,
        "mean": [0.0] * N_SOFT + [*D_MEAN, 0.0, 0.0, 0.0],
        "sd": [1e-6] * N_SOFT + [d_sd] * 3 + [50.0] * 3,
    }
    if applied is not None:
        warm["applied"] = applied
    st = InflightStage(0, InflightConfig(), "relative", "test", True, NORM, warm)
    assert st.warm_started
    return st


def _sigma_deg(d_sd: float) -> float:
    # the hard iron's component across the horizontal field (0.5 NORM by default) turns the heading
    return math.degrees(d_sd / (0.5 * NORM))


def test_stored_estimate_not_yet_applied_is_not_applied_when_uncertain() -> None:
    d_sd = 150.0
    assert 2.0 * MAX_APPLY_HEADING_SIGMA_DEG > _sigma_deg(d_sd) > MAX_APPLY_HEADING_SIGMA_DEG
    st = _stage(d_sd, applied=False)
    # the 2-sigma rule alone would take it: 135 deg of change against ~40 deg of uncertainty
    assert st.output(1.0, FIELD, 0.0, ()) is None
    assert not st.applied
    sol = st.solution
    assert sol is not None and math.isclose(sol.heading_sigma_deg, _sigma_deg(d_sd), rel_tol=1e-6)
    assert sol.heading_sigma_deg < 135.0 / 2.0  # what the 2-sigma rule (APPLY_Z) alone would have accepted


def test_stored_estimate_not_yet_applied_is_applied_once_certain_and_turned() -> None:
    """Certain is not enough for the relative form: the heading must also have covered a quarter turn in
    this run (the hard iron is told from the Earth field only by rotation)."""
    st = _stage(10.0, applied=False)
    assert st.output(1.0, FIELD, 0.0, ()) is None  # certain, but not turned yet
    assert "yaw span" in st.why_not()
    for k in range(100):  # a slow turn through 99 deg, no pairs added (no rotation source for them)
        yaw = math.radians(float(k))
        st._span.track(np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0],
                                [0.0, 0.0, 1.0]]))  # fmt: skip
    out = st.output(2.0, FIELD, 0.0, ())
    assert out is not None and st.applied
    np.testing.assert_allclose(out.coeffs[9:], D_MEAN)


def test_stored_estimate_that_was_applied_is_applied_from_the_first_sample() -> None:
    st = _stage(150.0, applied=True)
    assert st.applied
    assert st.output(1.0, FIELD, 0.0, ()) is not None
    state = st.state()
    assert state is not None and state["applied"] is True
    assert not _stage(150.0, applied=None).applied  # a file without the flag: not applied until it passes


def test_unobserved_parameters_stay_within_the_physical_prior_across_runs() -> None:
    """Each saved state inflates its sd (the vehicle may have changed), but what no run observed (theta on a
    disarmed log) stays at the first run's physical prior instead of doubling with every run."""
    from magcomp.core.inflight import InflightEstimator, InflightParams

    p = InflightParams()
    warm = None
    for _ in range(5):
        est = InflightEstimator("relative", 0, p, NORM, warm)
        warm = est.state()
    assert warm is not None
    np.testing.assert_allclose(
        warm[1][N_SOFT + 3 : N_SOFT + 6], p.sigma_theta_mgauss
    )  # theta: never observed
    np.testing.assert_allclose(warm[1][N_SOFT : N_SOFT + 3], p.sigma_d_mgauss)
    np.testing.assert_allclose(warm[1][:N_SYM], p.sigma_a)
    np.testing.assert_allclose(warm[1][N_SYM:N_SOFT], p.sigma_rot_rad)  # the mount's misalignment


def test_relative_form_says_when_the_motors_never_ran() -> None:
    """A disarmed log (throttle 0 throughout) with an attitude stream: the window-field rows take motors-on
    samples only, so the reason given is the motors, not a missing rotation source; with no attitude at all
    it is the rotation source."""
    disarmed = InflightStage(0, InflightConfig(), "relative", "test", True, NORM, None)
    no_att = InflightStage(0, InflightConfig(), "relative", "test", True, NORM, None)
    for k in range(200):
        yaw = math.radians(float(k))
        r_nb = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0],
                         [0.0, 0.0, 1.0]])  # fmt: skip
        y = r_nb.T @ np.asarray(FIELD)
        disarmed.feed(0.1 * k, y, 0.0, (), None, None, r_nb)
        no_att.feed(0.1 * k, y, 0.0, (), None, None, None)
    assert disarmed.n_rows == 0
    assert "motors never ran" in disarmed.why_not()
    assert "no rotation source" in no_att.why_not()
