import cv2
import jax
import jax.numpy as jnp
import jaxlie
import jaxloc
import numpy as np
import pytest
from jaxloc._solvers.mutual import mutual_localization


def _random_rotation(rng, angle=None):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0, np.pi) if angle is None else angle
    return jaxlie.SO3.exp(jnp.asarray(axis * angle))


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.3, np.pi - 1e-7, np.pi])
def test_rotation_angle_and_finite_gradients(angle):
    rng = np.random.default_rng(0)
    R = _random_rotation(rng, angle)
    assert float(jaxloc.rotation_angle(R)) == pytest.approx(angle, abs=1e-7)

    def f(tangent):
        return jaxloc.rotation_error(R, R @ jaxlie.SO3.exp(tangent))

    for tangent in (jnp.zeros(3), jnp.array([1e-8, 0.0, 0.0])):
        g = jax.grad(f)(tangent)
        assert np.all(np.isfinite(np.asarray(g)))
    g_at_pi = jax.grad(lambda t: jaxloc.rotation_angle(jaxlie.SO3.exp(t)))(jnp.array([np.pi, 0, 0]))
    assert np.all(np.isfinite(np.asarray(g_at_pi)))


def test_rotation_error_matches_matrix_formula():
    rng = np.random.default_rng(1)
    for _ in range(20):
        A, B = _random_rotation(rng), _random_rotation(rng)
        M = A.as_matrix().T @ B.as_matrix()
        expected = np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1))
        assert float(jaxloc.rotation_error(A, B)) == pytest.approx(expected, abs=1e-7)


def test_ypr_round_trip_and_convention():
    ypr = jnp.array([30.0, -20.0, 10.0])
    R = jaxloc.rotation_from_ypr(ypr)
    np.testing.assert_allclose(jaxloc.ypr_from_rotation(R), ypr, atol=1e-10)
    y, p, r = np.deg2rad(np.asarray(ypr))
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    np.testing.assert_allclose(R.as_matrix(), Rz @ Ry @ Rx, atol=1e-12)
    np.testing.assert_allclose(
        jaxloc.ypr_from_rotation(R, degrees=False), np.deg2rad(np.asarray(ypr)), atol=1e-12
    )
    with pytest.raises(ValueError, match="ypr"):
        jaxloc.rotation_from_ypr(jnp.zeros(2))


@pytest.mark.parametrize("n", [2, 3, 10])
def test_kabsch_recovers_rotation_with_two_or_more_pairs(n):
    rng = np.random.default_rng(n)
    R = _random_rotation(rng)
    a = jnp.asarray(rng.normal(size=(n, 3)))
    b = jax.vmap(R.apply)(a)
    R_hat = jaxloc.kabsch(a, b)
    assert float(jaxloc.rotation_error(R, R_hat)) < 1e-10
    assert np.linalg.det(R_hat.as_matrix()) == pytest.approx(1.0)
    # Weights: a zero weight ignores a corrupted pair.
    b_bad = b.at[0].set(-b[0] + 1.0)
    if n > 2:
        w = jnp.ones(n).at[0].set(0.0)
        assert float(jaxloc.rotation_error(R, jaxloc.kabsch(a, b_bad, w))) < 1e-10
    g = jax.grad(lambda a: jaxloc.kabsch(a, b).as_matrix().sum())(a)
    assert np.all(np.isfinite(np.asarray(g)))


def test_kabsch_returns_a_proper_rotation_for_reflected_data():
    rng = np.random.default_rng(4)
    a = jnp.asarray(rng.normal(size=(5, 3)))
    b = a * jnp.array([[1.0, 1.0, -1.0]])  # a reflection: best proper rotation, det +1
    assert np.linalg.det(jaxloc.kabsch(a, b).as_matrix()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="at least 2"):
        jaxloc.kabsch(a[:1], b[:1])
    with pytest.raises(ValueError, match="shape"):
        jaxloc.kabsch(a, b[:, :2])


def test_opencv_rvec_tvec_round_trip_agrees_with_rodrigues():
    rng = np.random.default_rng(5)
    for _ in range(10):
        rvec, tvec = rng.normal(size=3), rng.normal(size=3)
        T = jaxloc.pose_from_opencv(rvec.reshape(3, 1), tvec.reshape(3, 1))
        R_cv, _ = cv2.Rodrigues(rvec)
        np.testing.assert_allclose(T.rotation().as_matrix(), R_cv, atol=1e-12)
        np.testing.assert_allclose(T.translation(), tvec, atol=1e-12)
        r2, t2 = jaxloc.pose_to_opencv(T)
        np.testing.assert_allclose(cv2.Rodrigues(np.asarray(r2))[0], R_cv, atol=1e-12)
        np.testing.assert_allclose(t2, tvec, atol=1e-12)
    with pytest.raises(ValueError, match="rvec"):
        jaxloc.pose_from_opencv(np.zeros(2), np.zeros(3))


@pytest.mark.parametrize("ref", [0, 1, 2])
def test_mutual_localization_exact_for_every_reference(ref):
    rng = np.random.default_rng(10 + ref)
    for _ in range(5):
        Ts = [jaxlie.SE3.exp(jnp.asarray(rng.normal(size=6))) for _ in range(3)]
        b = np.zeros((3, 3, 3))
        for i in range(3):
            for j in range(3):
                if i != j:
                    p = np.asarray(Ts[i].inverse() @ Ts[j].translation())
                    b[i, j] = p / np.linalg.norm(p)
        sol = mutual_localization(jnp.asarray(b), ref)
        truth = [Ts[ref].inverse() @ T for T in Ts]
        other = (ref + 1) % 3
        scale = np.linalg.norm(truth[other].translation()) / np.linalg.norm(
            sol.T_ref_body.translation()[other]
        )
        for m in range(3):
            np.testing.assert_allclose(
                scale * sol.T_ref_body.translation()[m], truth[m].translation(), atol=1e-10
            )
            R_m = jaxlie.SO3(sol.T_ref_body.rotation().wxyz[m])
            assert float(jaxloc.rotation_error(R_m, truth[m].rotation())) < 1e-10
        assert sol.result == jaxloc.RESULTS.successful


def test_mutual_localization_bad_input():
    with pytest.raises(ValueError, match="ref"):
        mutual_localization(jnp.ones((3, 3, 3)), 3)
    with pytest.raises(ValueError, match="shape"):
        mutual_localization(jnp.ones((2, 3, 3)))
    nan = jnp.full((3, 3, 3), jnp.nan)
    sol = mutual_localization(nan, throw=False)
    assert sol.result == jaxloc.RESULTS.nonfinite_observation
    assert np.all(np.isfinite(np.asarray(sol.T_ref_body.wxyz_xyz)))
