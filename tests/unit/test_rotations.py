import numpy as np
import pytest

from magcomp.core import rotations as rot


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_quat_dcm_euler_roundtrip(rng: np.random.Generator) -> None:
    for _ in range(50):
        roll, yaw = rng.uniform(-np.pi, np.pi, 2)
        pitch = rng.uniform(-1.5, 1.5)
        r = rot.dcm_from_euler(roll, pitch, yaw)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        q = rot.quat_from_dcm(r)
        np.testing.assert_allclose(rot.dcm_from_quat(q), r, atol=1e-12)
        np.testing.assert_allclose(rot.euler_from_quat(q), (roll, pitch, yaw), atol=1e-9)


def test_so3_exp_log_inverse_and_strapdown_eq18(rng: np.random.Generator) -> None:
    for _ in range(50):
        phi = rng.normal(size=3)
        phi *= rng.uniform(0.0, 3.0) / np.linalg.norm(phi)
        np.testing.assert_allclose(rot.so3_log(rot.so3_exp(phi)), phi, atol=1e-9)
        np.testing.assert_allclose(rot.dcm_from_quat(rot.quat_exp(phi)), rot.so3_exp(phi), atol=1e-12)
    # eq. (18): integrating a constant body rate for 1 s equals the exponential map
    w = np.array([0.3, -0.2, 0.9])
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for _ in range(100):
        q = rot.quat_integrate_body_rate(q, w, 0.01)
    np.testing.assert_allclose(rot.dcm_from_quat(q), rot.so3_exp(w), atol=1e-12)


def test_frd_ned_convention_nose_east_and_down_vector() -> None:
    # yaw +90 deg: body x (nose) points east in NED
    r = rot.dcm_from_euler(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # roll +90 deg (right wing down): NED down is along body -y
    q = rot.quat_from_euler(np.pi / 2, 0.0, 0.3)
    np.testing.assert_allclose(rot.down_b_from_quat(q), [0, 1, 0], atol=1e-12)


def test_batch_dcm_equals_single(rng: np.random.Generator) -> None:
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    batch = rot.dcms_from_quats(q)
    for qi, ri in zip(q, batch, strict=True):
        np.testing.assert_allclose(ri, rot.dcm_from_quat(qi), atol=1e-14)


def test_batch_quat_multiply_equals_single(rng: np.random.Generator) -> None:
    p = rng.normal(size=(20, 4))
    q = rng.normal(size=(20, 4))
    batch = rot.quats_multiply(p, q)
    assert batch.shape == (20, 4)
    for pi, qi, bi in zip(p, q, batch, strict=True):
        np.testing.assert_allclose(bi, rot.quat_multiply(pi, qi), atol=1e-14)


def test_batch_euler_equals_single(rng: np.random.Generator) -> None:
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    from_quats = rot.euler_from_quats(q)
    from_dcms = rot.euler_from_dcms(rot.dcms_from_quats(q))
    assert from_quats.shape == (20, 3)
    np.testing.assert_array_equal(from_quats, from_dcms)
    for qi, ei in zip(q, from_quats, strict=True):
        np.testing.assert_allclose(ei, rot.euler_from_quat(qi), atol=1e-12)


def test_batch_quats_from_euler_same_rotation_as_single(rng: np.random.Generator) -> None:
    roll = rng.uniform(-np.pi, np.pi, 20)
    pitch = rng.uniform(-1.5, 1.5, 20)
    yaw = rng.uniform(-np.pi, np.pi, 20)
    batch = rot.quats_from_euler(roll, pitch, yaw)
    np.testing.assert_allclose(np.linalg.norm(batch, axis=1), 1.0, atol=1e-14)
    for k in range(20):
        single = rot.quat_from_euler(roll[k], pitch[k], yaw[k])
        # q and -q are the same rotation; the batch form does not normalise the sign
        sign = 1.0 if batch[k, 0] >= 0.0 else -1.0
        np.testing.assert_allclose(sign * batch[k], single, atol=1e-12)
    np.testing.assert_allclose(rot.euler_from_quats(batch), np.stack([roll, pitch, yaw], axis=1), atol=1e-9)


def test_batch_dcm_same_bits_as_scipy_and_rejects_zero_norm(rng: np.random.Generator) -> None:
    """dcms_from_quats is written out (no scipy.spatial import on the replay path) with scipy's arithmetic:
    the same bits on unnormalised and unit quaternions, and the same error on a zero or NaN norm."""
    from scipy.spatial.transform import Rotation

    q = rng.normal(size=(20_000, 4)) * rng.uniform(0.2, 5.0, size=(20_000, 1))
    q[:5000] /= np.linalg.norm(q[:5000], axis=1)[:, None]
    got = rot.dcms_from_quats(q)
    want = Rotation.from_quat(q, scalar_first=True).as_matrix()
    assert got.shape == (20_000, 3, 3)
    assert np.array_equal(got, want)
    for bad in (0.0, np.nan):
        with pytest.raises(ValueError):
            rot.dcms_from_quats(np.array([[1.0, 0.0, 0.0, 0.0], [bad, 0.0, 0.0, 0.0]]))
