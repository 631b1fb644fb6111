"""Batched Jacobi eigendecomposition (kernels/eigen.py) on the CPU, against
numpy.linalg.eigh and, where LAPACK's own error would dominate, a 40-digit mpmath
reference. eps = 2.2e-16 (float64); |H| is the 2-norm, max |eigenvalue|."""

import mpmath
import numpy as np
import pytest
import warp as wp

from tawarp.kernels.eigen import eigh_kernel

EPS = np.finfo(float).eps


def eigh(H):
    """(w, V) of the kernel for H (n, p, p) on the CPU."""
    n, p = H.shape[:2]
    w = wp.empty((n, p), dtype=wp.float64, device="cpu")
    V = wp.empty((n, p, p), dtype=wp.float64, device="cpu")
    wp.launch(eigh_kernel(p), dim=n, device="cpu", inputs=[wp.array(H, dtype=wp.float64, device="cpu"), w, V])
    return w.numpy(), V.numpy()


def spd(rng, n, p):
    """n random SPD p x p matrices A A^T, A (p, p + 3) standard normal (cond up to ~1e3)."""
    A = rng.standard_normal((n, p, p + 3))
    return A @ A.transpose(0, 2, 1)


def reference(H):
    """Eigenvalues of one float64 matrix, ascending, to 40 digits (mpmath), as float."""
    with mpmath.workdps(40):
        w = mpmath.eigsy(mpmath.matrix(H.tolist()), eigvals_only=True)
        return np.array(sorted(float(x) for x in w))


def check_decomposition(H, w, V, tol=1e-13):
    """Ascending eigenvalues; V orthonormal and V diag(w) V^T = H, each to tol |H|."""
    scale = np.abs(w).max(axis=1)[:, None, None]
    assert np.all(np.diff(w, axis=1) >= 0)
    p = H.shape[1]
    assert np.max(np.abs(V.transpose(0, 2, 1) @ V - np.eye(p))) < tol
    assert np.max(np.abs((V * w[:, None, :]) @ V.transpose(0, 2, 1) - H) / scale) < tol


@pytest.mark.parametrize("p", range(1, 9))
def test_random_spd_matches_numpy(p):
    """300 random SPD matrices per p (3 seeds): eigenvalues within 1e-12 |H| of NumPy's
    (both are backward stable: each within a few p eps |H| of the truth); eigenvectors of
    eigenvalues separated by more than 1e-3 |H| from the others equal NumPy's up to sign,
    |v_numpy . v| within 1e-10 of 1 (their angle is below ~p eps |H| / gap ~ 1e-12);
    reconstruction and orthonormality to 1e-13."""
    for seed in range(3):
        rng = np.random.default_rng(100 * p + seed)
        H = spd(rng, 100, p)
        w, V = eigh(H)
        w0, V0 = np.linalg.eigh(H)
        wmax = np.abs(w0).max(axis=1, keepdims=True)
        assert np.max(np.abs(w - w0) / wmax) < 1e-12
        check_decomposition(H, w, V)
        gap = np.full_like(w0, np.inf)
        for i in range(p):
            for j in range(p):
                if i != j:
                    gap[:, i] = np.minimum(gap[:, i], np.abs(w0[:, i] - w0[:, j]))
        apart = gap / wmax > 1e-3
        assert apart.mean() > 0.9  # the test compares most eigenvectors
        dots = np.abs(np.einsum("nik,nik->nk", V0, V))
        assert np.max(np.abs(dots[apart] - 1.0)) < 1e-10


def test_padded_parameter_gives_an_exact_zero():
    """A zero row and column (a parameter with no effect, or a padded one) is left alone by
    every rotation: eigenvalue exactly 0 with eigenvector exactly +-e_k, first; the rest
    is the decomposition of the other rows (eigenvalues within 1e-12 |H| of NumPy's)."""
    rng = np.random.default_rng(7)
    for p in (2, 3, 5, 8):
        H = spd(rng, 20, p)
        k = np.arange(20) % p
        H[np.arange(20), k, :] = 0.0
        H[np.arange(20), :, k] = 0.0
        w, V = eigh(H)
        assert np.all(w[:, 0] == 0.0) and np.all(w[:, 1:] > 0.0)
        assert np.all(np.abs(V[np.arange(20), :, 0]) == np.eye(p)[k])
        w0 = np.linalg.eigh(H)[0]
        assert np.max(np.abs(w - w0) / np.abs(w0).max(axis=1, keepdims=True)) < 1e-12
        check_decomposition(H, w, V)


def test_rank_deficient():
    """J with a column the sum of two others (a pair of parameters that only act
    together): H = J^T J exactly singular (integer J, exact products). The null eigenvalue
    comes out at most 4 p eps |H| from 0 (backward error; far below the 1e-14 |H| that
    the covariance calls undetermined), its eigenvector is the null vector (a - b + c) / sqrt 3
    to 1e-13, and the decomposition holds to 1e-13."""
    rng = np.random.default_rng(8)
    for p in (3, 4, 8):
        J = rng.integers(-9, 10, size=(50, 12, p)).astype(float)
        J[:, :, 2] = J[:, :, 0] + J[:, :, 1]
        H = J.transpose(0, 2, 1) @ J
        w, V = eigh(H)
        wmax = np.abs(w).max(axis=1)
        assert np.max(np.abs(w[:, 0]) / wmax) < 4 * p * EPS
        null = np.zeros(p)
        null[:3] = np.array([1.0, 1.0, -1.0]) / np.sqrt(3.0)
        assert np.max(np.abs(np.abs(V[:, :, 0] @ null) - 1.0)) < 1e-13
        check_decomposition(H, w, V)


def test_diagonal_input_is_exact():
    """A diagonal matrix (repeated and zero entries included) needs no rotation: its
    eigenvalues are the diagonal sorted and V a permutation matrix, both exactly."""
    rng = np.random.default_rng(9)
    for p in (1, 4, 8):
        d = rng.choice([0.0, 1e-12, 0.5, 0.5, 3.0, 1e6], size=(30, p))
        H = np.zeros((30, p, p))
        H[:, np.arange(p), np.arange(p)] = d
        w, V = eigh(H)
        assert np.array_equal(w, np.sort(d, axis=1))
        assert np.all((V == 0.0) | (V == 1.0)) and np.all(V.sum(axis=1) == 1.0) and np.all(V.sum(axis=2) == 1.0)
        assert np.array_equal((V * w[:, None, :]) @ V.transpose(0, 2, 1), H)


def test_ill_conditioned_graded_matrix_keeps_small_eigenvalues():
    """cond(H) ~ 1e14 from badly scaled parameters, H = S A S with S = diag(1 .. 1e-7) and
    A unit-diagonal, cond(A) <= 20: Jacobi's relative threshold gives every eigenvalue,
    the smallest (~1e-14 |H|) included, to relative error O(p eps cond(A)) (Demmel &
    Veselic 1992), asserted as 4 p eps cond(A) against the 40-digit reference. (LAPACK's
    bound for the smallest is only eps |H| / lambda ~ 1.)"""
    rng = np.random.default_rng(10)
    for p in (2, 3, 5, 8):
        B = rng.standard_normal((5, 4 * p, p))
        A = B.transpose(0, 2, 1) @ B
        d = 1.0 / np.sqrt(np.einsum("nii->ni", A))
        A = A * d[:, :, None] * d[:, None, :]
        kappa = np.linalg.cond(A)
        assert kappa.max() < 20
        S = np.logspace(0, -7, p)
        H = A * S[:, None] * S[None, :]
        w, V = eigh(H)
        assert np.all(w[:, -1] / w[:, 0] > 1e13)
        for i in range(5):
            ref = reference(H[i])
            assert np.max(np.abs(w[i] - ref) / ref) < 4 * p * EPS * kappa[i]
        check_decomposition(H, w, V)


def test_ill_conditioned_unscaled_matrix_is_backward_stable():
    """cond(H) = 1e14 with no scaling to exploit, H = Q diag(1 .. 1e-14) Q^T with Q a
    random rotation: the guarantee of any stable method (Jacobi's included) is an absolute
    error of p eps |H| per eigenvalue, asserted against the 40-digit reference of the
    rounded H; the smallest eigenvalue is then known to ~p eps cond ~ 0.1 relative only."""
    rng = np.random.default_rng(11)
    for p in (2, 3, 5, 8):
        Q = np.linalg.qr(rng.standard_normal((5, p, p)))[0]
        H = (Q * np.logspace(0, -14, p)) @ Q.transpose(0, 2, 1)
        w, V = eigh(H)
        for i in range(5):
            ref = reference(H[i])
            assert np.max(np.abs(w[i] - ref)) < p * EPS * np.abs(ref).max()
        check_decomposition(H, w, V)


def test_non_finite_input_gives_nan_and_spares_the_others():
    """A NaN or infinite entry (of the lower triangle: the one read, as NumPy's default
    UPLO='L') gives NaN eigenvalues and eigenvectors for that matrix only; the other
    matrices of the batch are exactly as in a batch without it. The upper triangle is
    not read."""
    rng = np.random.default_rng(12)
    p = 4
    H = spd(rng, 8, p)
    w_clean, V_clean = eigh(H)
    bad = H.copy()
    bad[1, 0, 0] = np.nan
    bad[3, 2, 1] = np.inf
    bad[5, 3, 0] = -np.inf
    w, V = eigh(bad)
    hit = np.zeros(8, dtype=bool)
    hit[[1, 3, 5]] = True
    assert np.all(np.isnan(w[hit])) and np.all(np.isnan(V[hit]))
    assert np.array_equal(w[~hit], w_clean[~hit]) and np.array_equal(V[~hit], V_clean[~hit])
    upper = H.copy()
    upper[:, 0, 3] = np.nan
    w, V = eigh(upper)
    assert np.array_equal(w, w_clean) and np.array_equal(V, V_clean)
