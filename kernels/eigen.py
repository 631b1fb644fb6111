"""Eigendecomposition of batches of small symmetric matrices, one thread per matrix.

:func:`eigh_kernel` ``(p)`` is :func:`numpy.linalg.eigh` for N symmetric p x p matrices
(p <= 8; :func:`tawarp.fit.estimate.covariance` decomposes each fit's ``H = J^T J``
with it): eigenvalues ascending, eigenvectors as columns, the lower triangle read. NumPy loops LAPACK once per
matrix on the host; here the matrix lives in registers of its thread.

Why cyclic Jacobi rather than LAPACK's reduction to tridiagonal form:

* *accuracy*: for a positive definite matrix, Jacobi with the relative threshold below
  finds every eigenvalue to a relative error of order ``p eps kappa(A)``, A the matrix
  scaled to unit diagonal (Demmel & Veselic, SIAM J. Matrix Anal. Appl. 13 (1992) 1204),
  where the tridiagonal methods guarantee ``p eps |H| / lambda``: a parameter badly scaled
  against the others (the common cause of a large condition number of J^T J) keeps its
  small eigenvalue, and so its variance, accurate. A matrix still ill-conditioned after
  that scaling gets the absolute error ``p eps |H|`` of any stable method.
* *simple*: plane rotations of a p x p matrix in registers; no reduction, shifts or
  deflation.
* *fixed work per thread*: a sweep visits the same p (p - 1) / 2 pairs for every matrix
  and convergence is quadratic, so the sweep counts of a batch differ by a few (for
  p = 3: 3 - 5, for p = 8: 6 - 9, the last one rotating nothing) and the threads of a
  warp stay together.

Rotation (i, j) is skipped when ``|a_ij| <= TOL sqrt(|a_ii|) sqrt(|a_jj|)`` (the threshold
of the accuracy result; every off-diagonal entry then is below ``TOL |H|`` too); the
sweeps stop when one rotates nothing, or after :data:`MAX_SWEEPS`. A matrix with a NaN or
infinite entry gets NaN eigenvalues and eigenvectors. Everything is float64.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

#: relative threshold of a rotation (a few eps: rounding alone keeps the rotated entries there)
TOL = wp.constant(wp.float64(1e-15))
#: sweeps at most; quadratic convergence needs far fewer
MAX_SWEEPS = wp.constant(30)

_EIGH_KERNELS = {}


def eigh_kernel(p: int):
    """The batched eigendecomposition kernel for p x p matrices (cached per p).

    Inputs: ``H`` (n, p, p) symmetric (the lower triangle is read). Outputs: ``w`` (n, p)
    eigenvalues ascending, ``V`` (n, p, p) orthonormal eigenvectors as columns
    (``H V[:, :, k] = w[:, k] V[:, :, k]``), the signs arbitrary as in NumPy.
    """
    if p in _EIGH_KERNELS:
        return _EIGH_KERNELS[p]
    P = wp.constant(p)
    matp = wp.types.matrix(shape=(p, p), dtype=wp.float64)

    @wp.kernel(enable_backward=False, module="unique")
    def eigh(H: wp.array3d(dtype=wp.float64), w: wp.array2d(dtype=wp.float64), V: wp.array3d(dtype=wp.float64)):
        n = wp.tid()
        A = matp()
        finite = bool(True)
        for i in range(P):
            for j in range(i + 1):
                A[i, j] = H[n, i, j]
                A[j, i] = H[n, i, j]
                finite = finite and wp.isfinite(H[n, i, j])
        if not finite:
            for i in range(P):
                w[n, i] = wp.float64(wp.nan)
                for j in range(P):
                    V[n, i, j] = wp.float64(wp.nan)
            return
        Q = wp.identity(n=P, dtype=wp.float64)
        sweeps = int(0)
        rotations = int(1)
        while rotations > 0 and sweeps < MAX_SWEEPS:
            rotations = int(0)
            sweeps += 1
            for i in range(P - 1):
                for j in range(i + 1, P):
                    aij = A[i, j]
                    # sqrt of each factor: their product may overflow or underflow
                    if wp.abs(aij) > TOL * wp.sqrt(wp.abs(A[i, i])) * wp.sqrt(wp.abs(A[j, j])):
                        rotations += 1
                        # Rutishauser's rotation: t = tan of the angle that zeroes a_ij, the
                        # smaller root; the diagonal moves by exactly t a_ij
                        theta = wp.float64(0.5) * (A[j, j] - A[i, i]) / aij
                        t = wp.float64(0.5) / theta  # the limit, where theta^2 would overflow
                        if wp.abs(theta) < wp.float64(1e150):
                            t = wp.float64(1.0) / (wp.abs(theta) + wp.sqrt(theta * theta + wp.float64(1.0)))
                            if theta < wp.float64(0.0):
                                t = -t
                        c = wp.float64(1.0) / wp.sqrt(t * t + wp.float64(1.0))
                        s = t * c
                        tau = s / (wp.float64(1.0) + c)
                        A[i, i] = A[i, i] - t * aij
                        A[j, j] = A[j, j] + t * aij
                        A[i, j] = wp.float64(0.0)
                        A[j, i] = wp.float64(0.0)
                        for r in range(P):
                            if r != i and r != j:
                                g = A[r, i]
                                h = A[r, j]
                                A[r, i] = g - s * (h + g * tau)
                                A[i, r] = A[r, i]
                                A[r, j] = h + s * (g - h * tau)
                                A[j, r] = A[r, j]
                            g = Q[r, i]
                            h = Q[r, j]
                            Q[r, i] = g - s * (h + g * tau)
                            Q[r, j] = h + s * (g - h * tau)
        # ascending order (selection sort: p <= 8)
        for i in range(P):
            k = i
            for j in range(i + 1, P):
                if A[j, j] < A[k, k]:
                    k = j
            w[n, i] = A[k, k]
            A[k, k] = A[i, i]
            for r in range(P):
                V[n, r, i] = Q[r, k]
                Q[r, k] = Q[r, i]

    _EIGH_KERNELS[p] = eigh
    return eigh
