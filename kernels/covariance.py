"""Parameter covariance of batched least-squares solutions, one thread per problem
(:func:`tawarp.fit.estimate.covariance`).

From the eigendecomposition ``H = V diag(w) V^T`` of ``J^T J`` in the scaled variables z
(:mod:`.eigen`, eigenvalues ascending) the kernel of :func:`covariance_kernel` forms

* ``cond = max |w| / w_0`` (inf unless ``w_0 > 0``), the 2-norm condition number of H;
* ``cov_z = V diag(1/w) V^T`` over the determined directions; a direction with
  ``w_j <= SINGULAR max |w|`` is undetermined and makes every entry (i, k) it touches
  (``|V_ij| |V_kj|`` summed over such j above :data:`INFLUENCE`) infinite;
* the delta method to natural units, ``unit = D cov_z D`` with ``D = diag(dv/dz)``, the
  covariance ``cov = s^2 unit``, ``std = sqrt |diag cov|`` and the correlation
  ``unit_ik / sqrt(|unit_ii| |unit_kk|)`` (independent of s^2, so defined for exact data;
  1 on the diagonal).

A non-finite H (NaN eigenvalues and eigenvectors from :mod:`.eigen`) determines no
direction: cond, cov and std are inf, the off-diagonal correlations NaN. Everything is
float64.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

#: eigenvalues at or below this fraction of the largest are undetermined directions (the
#: rounding of J^T J in float64)
SINGULAR = wp.constant(wp.float64(1e-14))
#: |V_ij| |V_kj| above this puts undetermined direction j into entry (i, k)
INFLUENCE = wp.constant(wp.float64(1e-8))

_COVARIANCE_KERNELS = {}


def covariance_kernel(p: int):
    """The covariance kernel for p parameters (cached per p).

    Inputs: ``w`` (n, p) eigenvalues ascending and ``V`` (n, p, p) eigenvectors as columns
    of H = J^T J, ``D`` (n, p) dv/dz at the solution, ``s2`` (n,) residual variance.
    Outputs: ``cov`` (n, p, p) natural units, ``std`` (n, p), ``corr`` (n, p, p),
    ``cond`` (n,).
    """
    if p in _COVARIANCE_KERNELS:
        return _COVARIANCE_KERNELS[p]
    P = wp.constant(p)
    vecp = wp.types.vector(length=p, dtype=wp.float64)
    matp = wp.types.matrix(shape=(p, p), dtype=wp.float64)

    @wp.kernel(enable_backward=False, module="unique")
    def covariance(
        w: wp.array2d(dtype=wp.float64),
        V: wp.array3d(dtype=wp.float64),
        D: wp.array2d(dtype=wp.float64),
        s2: wp.array(dtype=wp.float64),
        cov: wp.array3d(dtype=wp.float64),
        std: wp.array2d(dtype=wp.float64),
        corr: wp.array3d(dtype=wp.float64),
        cond: wp.array(dtype=wp.float64),
    ):
        n = wp.tid()
        inf = wp.float64(wp.inf)
        wmax = wp.max(wp.abs(w[n, 0]), wp.abs(w[n, P - 1]))  # ascending: the largest |w| is at an end
        cond[n] = inf
        if w[n, 0] > wp.float64(0.0):
            cond[n] = wmax / w[n, 0]
        inv = vecp()  # 1/w_j of the determined directions, 0 for the others
        undet = vecp()  # 1 for the undetermined ones (every one when w is NaN)
        for j in range(P):
            if w[n, j] > SINGULAR * wmax:
                inv[j] = wp.float64(1.0) / w[n, j]
            else:
                undet[j] = wp.float64(1.0)
        U = matp()
        for i in range(P):
            for k in range(P):
                cz = wp.float64(0.0)
                touch = wp.float64(0.0)
                for j in range(P):
                    cz += V[n, i, j] * inv[j] * V[n, k, j]
                    touch += wp.abs(V[n, i, j]) * undet[j] * wp.abs(V[n, k, j])
                # "not <=": a NaN V (non-finite H, no direction known) touches every entry
                if not (touch <= INFLUENCE):
                    cz = inf
                U[i, k] = cz * D[n, i] * D[n, k]
                cov[n, i, k] = U[i, k] * s2[n]
        for i in range(P):
            std[n, i] = wp.sqrt(wp.abs(U[i, i] * s2[n]))
            for k in range(P):
                corr[n, i, k] = U[i, k] / (wp.sqrt(wp.abs(U[i, i])) * wp.sqrt(wp.abs(U[k, k])))
            corr[n, i, i] = wp.float64(1.0)

    _COVARIANCE_KERNELS[p] = covariance
    return covariance
