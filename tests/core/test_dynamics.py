import numpy as np

from onboard.core.dynamics import predict_cov, predict_mean


def test_closed_form_equals_recursion(model, rng):
    """Eq. (6), literally, against the step-by-step recursion."""
    A, B, Q = model.A, model.B, model.Q
    mu0 = rng.normal(size=6) * 100
    S0 = np.diag(rng.uniform(1, 50, size=6))
    U = rng.uniform(-6000, 6000, size=(20, 3))
    means, covs = predict_mean(model, mu0, U), predict_cov(model, S0, 20)
    for tau in range(20):
        mu = np.linalg.matrix_power(A, tau + 1) @ mu0 + sum(
            np.linalg.matrix_power(A, tau - k) @ B @ U[k] for k in range(tau + 1))
        Ap = np.linalg.matrix_power(A, tau + 1)
        S = Ap @ S0 @ Ap.T + sum(
            np.linalg.matrix_power(A, tau - k) @ Q @ np.linalg.matrix_power(A, tau - k).T for k in range(tau + 1))
        np.testing.assert_allclose(means[tau], mu, rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(covs[tau], S, rtol=1e-10, atol=1e-8)


def test_paper_matrices(model):
    assert model.A[0, 3] == 1.0 and model.A[3, 3] == 0.8
    assert model.B[3, 0] == 1.0 / 1300
    # terminal speed under full force with friction: u / (m eps)
    v = np.zeros(6)
    for _ in range(200):
        v = model.A @ v + model.B @ np.array([6000.0, 0, 0])
    assert abs(v[3] - 6000 / (1300 * 0.2)) < 1e-6
