import math

import numpy as np
import pytest

from flight.quat import (quats_to_euler, quat_conjugate, quat_from_euler, quat_from_rotation, quat_integrate, quat_multiply,
                         quat_normalize, quat_to_euler, quat_to_rotation, rotate_vector, wrap_angle,
                         wrap_angle_float)


def rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_euler_matches_zyx_matrix_and_round_trips():
    rng = np.random.default_rng(0)
    for _ in range(200):
        roll, yaw = rng.uniform(-np.pi, np.pi, 2)
        pitch = rng.uniform(-1.5, 1.5)
        q = quat_from_euler(roll, pitch, yaw)
        np.testing.assert_allclose(quat_to_rotation(q), rz(yaw) @ ry(pitch) @ rx(roll), atol=1e-12)
        np.testing.assert_allclose(quat_to_euler(q), (roll, pitch, yaw), atol=1e-9)


def test_multiply_composes_rotations_and_conjugate_inverts():
    a = quat_from_euler(0.3, -0.2, 1.0)
    b = quat_from_euler(-1.1, 0.4, -2.0)
    np.testing.assert_allclose(quat_to_rotation(quat_multiply(a, b)),
                               quat_to_rotation(a) @ quat_to_rotation(b), atol=1e-12)
    np.testing.assert_allclose(quat_multiply(a, quat_conjugate(a)), [1, 0, 0, 0], atol=1e-12)


def test_rotate_vector_body_to_world():
    q = quat_from_euler(0.0, 0.0, np.pi / 2)  # yaw 90 deg: body forward points north (+y)
    np.testing.assert_allclose(rotate_vector(q, [1, 0, 0]), [0, 1, 0], atol=1e-12)
    vs = np.eye(3)
    np.testing.assert_allclose(rotate_vector(q, vs), vs @ quat_to_rotation(q).T, atol=1e-12)


def test_normalize():
    np.testing.assert_allclose(quat_normalize([2, 0, 0, 0]), [1, 0, 0, 0])
    with pytest.raises(ValueError):
        quat_normalize([0, 0, 0, 0])


def test_wrap_angle_one_formula_for_floats_numpy_and_jax():
    """[-pi, pi), and the float, numpy and jax.numpy forms give the same bits (the 200/400 Hz
    loops use the float form, the batch code the array forms)."""
    import jax.numpy as jnp
    rng = np.random.default_rng(3)
    a = np.concatenate([rng.uniform(-20.0, 20.0, 2000), [0.0, -0.0, np.pi, -np.pi, 2 * np.pi, -3 * np.pi]])
    w = wrap_angle(a)
    assert w.dtype == np.float64 and np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    assert wrap_angle(np.pi) == -np.pi and wrap_angle(-np.pi) == -np.pi
    floats = np.array([wrap_angle_float(float(x)) for x in a])
    np.testing.assert_array_equal(floats.view(np.int64), w.view(np.int64))
    assert type(wrap_angle_float(1.0)) is float
    a32 = a.astype(np.float32)
    np.testing.assert_array_equal(np.asarray(wrap_angle(jnp.asarray(a32), jnp)),
                                  (a32 + np.float32(np.pi)) % np.float32(2 * np.pi) - np.float32(np.pi))


def test_quat_multiply_numpy_and_jax_give_the_same_product():
    """One product: numpy's (checked 4-vectors) and jax.numpy's (the iLQR model) agree."""
    import jax.numpy as jnp
    a = quat_from_euler(0.3, -0.2, 1.0)
    b = quat_from_euler(-1.1, 0.4, -2.0)
    np.testing.assert_allclose(np.asarray(quat_multiply(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32), jnp)),
                               quat_multiply(a, b), atol=1e-6)
    with pytest.raises(ValueError):
        quat_multiply(a, [1.0, 0.0, 0.0])


def test_quat_integrate_turns_by_the_body_rate():
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for _ in range(200):   # 0.5 s at 2 pi rad/s about body x: half a turn
        q = quat_integrate(q, [2 * math.pi, 0.0, 0.0], 1.0 / 400)
    assert abs(abs(quat_to_euler(q)[0]) - math.pi) < 1e-9
    # body rate: from a 90 deg yaw, a body-x turn is a world-y turn
    q = quat_integrate(quat_from_euler(0.0, 0.0, math.pi / 2), [0.3, 0.0, 0.0], 1.0)
    assert quat_to_rotation(q)[:, 2] == pytest.approx([math.sin(0.3), 0.0, math.cos(0.3)], abs=1e-12)


def test_quat_from_rotation_inverts_quat_to_rotation():
    rng = np.random.default_rng(2)
    for _ in range(200):
        q = quat_normalize(rng.normal(size=4))
        q = -q if q[0] < 0 else q
        np.testing.assert_allclose(quat_from_rotation(quat_to_rotation(q)), q, atol=1e-12)


def test_the_batch_euler_is_the_scalar_one_through_gimbal_lock():
    rng = np.random.default_rng(3)
    qs = rng.normal(size=(200, 4))
    qs[:3] = [quat_from_euler(0.3, math.pi / 2, -1.0), quat_from_euler(-2.0, -math.pi / 2, 0.5), [2.0, 0, 0, 0]]
    np.testing.assert_allclose(quats_to_euler(qs), [quat_to_euler(q) for q in qs], atol=1e-12)


def test_float_euler_and_norm_match_numpy_to_rounding():
    """quat_to_euler and roll_floats normalise in floats: the numbers of dividing by
    np.linalg.norm to the last bits (its SIMD kernels round differently on some CPUs)."""
    from flight.quat import roll_floats, unit_floats
    rng = np.random.default_rng(7)
    for _ in range(20000):
        q = rng.normal(size=4) * 10 ** rng.uniform(-3, 3)
        w, x, y, z = (q / np.linalg.norm(q)).tolist()
        roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        np.testing.assert_allclose(unit_floats(*q.tolist()), (w, x, y, z), rtol=1e-15, atol=1e-16)
        assert quat_to_euler(q)[0] == roll_floats(*q.tolist()) == pytest.approx(roll, rel=1e-12, abs=1e-12)
    with pytest.raises(ValueError, match="zero or non-finite"):
        roll_floats(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="zero or non-finite"):
        quat_to_euler([math.nan, 0.0, 0.0, 1.0])
