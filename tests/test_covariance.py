"""tawarp.fit.estimate.covariance (kernels/eigen.py + kernels/covariance.py on the CPU)
against the NumPy formulas it replaced, on a stand-in for Problems (the device, the
frequency count and dv/dz are all covariance reads of it)."""

from types import SimpleNamespace

import numpy as np

from tawarp.fit.estimate import covariance


def numpy_covariance(D, H, cost, dof, absolute_sigma=False):
    """The former host implementation (np.linalg.eigh and einsum), as the oracle."""
    n, p = D.shape
    s2 = np.ones(n) if absolute_sigma else cost / dof
    w, V = np.linalg.eigh(H)
    wmax = np.max(np.abs(w), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(w[:, 0] > 0, wmax / w[:, 0], np.inf)
        inv_w = np.where(w > 1e-14 * wmax[:, None], 1.0 / w, np.inf)
    with np.errstate(invalid="ignore"):
        cov_z = np.einsum("nij,nj,nkj->nik", V, np.where(np.isfinite(inv_w), inv_w, 0.0), V)
        sing = ~np.isfinite(inv_w)
        if sing.any():
            infl = np.einsum("nij,nj,nkj->nik", np.abs(V), sing.astype(float), np.abs(V)) > 1e-8
            cov_z = np.where(infl, np.inf, cov_z)
    unit = cov_z * D[:, :, None] * D[:, None, :]
    cov = unit * s2[:, None, None]
    std = np.sqrt(np.abs(np.einsum("nii->ni", cov)))
    su = np.sqrt(np.abs(np.einsum("nii->ni", unit)))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = unit / (su[:, :, None] * su[:, None, :])
    corr[:, np.arange(p), np.arange(p)] = 1.0
    return cov, std, corr, cond, s2, V


def problems(D, m=6):
    return SimpleNamespace(device="cpu", freqs=np.zeros(m), dv_dz=lambda z, pid: D[pid])


def batch(p, seed):
    """40 well-conditioned H (cond < 1e4) and 40 with a padded parameter (zero row and
    column), 20 exactly singular ones (a column of integer J the sum of two others, p >= 3),
    and H = 0; dv/dz spanning 1e-5 .. 1e2."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((80, p, p + 3))
    H = A @ A.transpose(0, 2, 1)
    k = np.arange(40) % p
    H[40 + np.arange(40), k, :] = 0.0
    H[40 + np.arange(40), :, k] = 0.0
    if p >= 3:
        J = rng.integers(-9, 10, size=(20, 12, p)).astype(float)
        J[:, :, 2] = J[:, :, 0] + J[:, :, 1]
        H = np.concatenate([H, J.transpose(0, 2, 1) @ J])
    H = np.concatenate([H, np.zeros((1, p, p))])
    n = H.shape[0]
    D = 10.0 ** rng.uniform(-5, 2, (n, p))
    return H, D, rng.uniform(1.0, 5.0, n)


def test_covariance_matches_the_numpy_formulas():
    """Every output of the device covariance equals the former NumPy one: the same
    entries infinite (an undetermined direction marks what it touches) and NaN, the
    finite ones to 1e-10 relative (cov, std: scaled by sqrt(cov_ii cov_kk); corr
    absolute), s2 exactly, V equal up to the sign of each column to 1e-10; cond to 1e-10
    relative below 1e14 and beyond it in both (a singular H's smallest eigenvalue is
    rounding, of either sign: cond ~1e16 or inf); for p = 1 .. 8 and both choices of s2."""
    for p in range(1, 9):
        H, D, cost = batch(p, p)
        n = H.shape[0]
        for absolute_sigma in (False, True):
            got = covariance(problems(D), np.arange(n), np.zeros((n, p)), H, cost, absolute_sigma)
            ref = numpy_covariance(D, H, cost, 8 * 6 - p, absolute_sigma)
            for a, b in zip(got, ref):
                assert a.shape == b.shape
            cov, std, corr, cond, s2, V = got
            rcov, rstd, rcorr, rcond, rs2, rV = ref
            for a, b in ((cov, rcov), (std, rstd), (corr, rcorr)):
                assert np.array_equal(np.isposinf(a), np.isposinf(b)) and np.array_equal(np.isnan(a), np.isnan(b))
            with np.errstate(invalid="ignore"):
                d = np.sqrt(np.abs(np.einsum("nii->ni", rcov)))
                scale = d[:, :, None] * d[:, None, :]
            fin = np.isfinite(rcov) & (scale < np.inf)
            assert np.max(np.abs(cov[fin] - rcov[fin]) / scale[fin], initial=0.0) < 1e-10
            fin = np.isfinite(rstd)
            assert np.max(np.abs(std[fin] - rstd[fin]) / rstd[fin], initial=0.0) < 1e-10
            fin = np.isfinite(rcorr)
            assert np.max(np.abs(corr[fin] - rcorr[fin]), initial=0.0) < 1e-10
            fin = rcond < 1e14
            assert np.array_equal(cond < 1e14, fin)
            assert np.max(np.abs(cond[fin] - rcond[fin]) / rcond[fin], initial=0.0) < 1e-10
            assert np.array_equal(s2, rs2)
            nz = n - 1  # H = 0: every direction undetermined, any orthonormal V is right
            assert np.max(np.abs(np.abs(np.einsum("nik,nik->nk", V[:nz], rV[:nz])) - 1.0)) < 1e-10


def test_padded_parameter_and_singular_pair():
    """A parameter with no effect (zero row and column of H) is itself the undetermined
    direction: infinite variance, and covariance and correlation 0 with the others, which keep
    the inverse of their own block (to 1e-12 scaled). A column of J that is the sum of two
    others makes the three undetermined together: every std and covariance inf."""
    H, D, cost = batch(3, 0)
    n = H.shape[0]
    cov, std, corr, cond, s2, V = covariance(problems(D), np.arange(n), np.zeros((n, 3)), H, cost)
    i, k = 40, 0  # problem 40: parameter 0 padded
    assert np.isinf(std[i, k]) and np.all(np.isfinite(std[i, 1:])) and cond[i] == np.inf
    assert np.all(cov[i, k, 1:] == 0.0) and np.all(corr[i, k, 1:] == 0.0)
    sub = np.linalg.inv(H[i, 1:, 1:]) * np.outer(D[i, 1:], D[i, 1:]) * s2[i]
    assert np.max(np.abs(cov[i, 1:, 1:] - sub) / np.sqrt(np.outer(np.diag(sub), np.diag(sub)))) < 1e-12
    assert np.all(np.abs(V[i, :, 0]) == [1.0, 0.0, 0.0])
    j = 80  # first exactly singular problem
    assert np.all(np.isinf(std[j])) and np.all(np.isinf(cov[j])) and cond[j] > 1e14  # w_0 is rounding


def test_non_finite_and_empty():
    """A NaN or infinite H (an evaluation that failed at the start) determines nothing:
    cond, std and every covariance entry inf, the off-diagonal correlations NaN (1 on the
    diagonal), V NaN; the other problems of the batch are untouched (NumPy's eigh raised
    LinAlgError for the whole batch when a matrix was all NaN). An empty batch gives
    empty outputs."""
    H, D, cost = batch(3, 1)
    n = H.shape[0]
    clean = covariance(problems(D), np.arange(n), np.zeros((n, 3)), H, cost)
    H[3] = np.nan
    H[7, 2, 1] = H[7, 1, 2] = np.inf
    cov, std, corr, cond, s2, V = covariance(problems(D), np.arange(n), np.zeros((n, 3)), H, cost)
    bad = np.isin(np.arange(n), [3, 7])
    assert np.all(np.isposinf(cov[bad])) and np.all(np.isposinf(std[bad])) and np.all(np.isposinf(cond[bad]))
    assert np.all(np.isnan(V[bad]))
    off = ~np.eye(3, dtype=bool)
    assert np.all(np.isnan(corr[bad][:, off])) and np.all(corr[bad][:, ~off] == 1.0)
    for a, b in zip((cov, std, corr, cond, s2, V), clean):
        assert np.array_equal(a[~bad], b[~bad], equal_nan=True)
    out = covariance(problems(D), np.arange(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0))
    assert [a.shape for a in out] == [(0, 3, 3), (0, 3), (0, 3, 3), (0,), (0,), (0, 3, 3)]
