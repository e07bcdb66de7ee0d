"""The least-spread direction of many small point neighbourhoods at once: the normal of each one's best-fit plane.

Local plane fits (stray points, the good scans' reference surface) need, for each of tens of thousands of
neighbourhoods, the smallest eigenvalue of a 3 x 3 scatter matrix and its eigenvector. ``numpy.linalg.eigh`` on a
stack of 3 x 3 matrices calls LAPACK once per matrix (about 1.7 us each on one core, 50 ms for a 30,000-point scan),
which made these fits a large share of a full-resolution scan's inspection. :func:`smallest_eigenpairs` solves the
3 x 3 case in closed form, vectorised over the stack, and hands the few matrices where the closed form is
ill-conditioned (a repeated smallest eigenvalue: a line of points, a single point, an isotropic blob) to
``numpy.linalg.eigh``.
"""
import numpy as np

# a smallest eigenvector from the cross product of two rows of A - lambda I is trusted when that cross product is
# at least this fraction of (lambda_max - lambda_min)^2; below it the two smallest eigenvalues (nearly) coincide, the
# direction is ill-defined, and LAPACK decides it as it always did
_CROSS_FRACTION = 1e-6


def smallest_eigenpairs(matrices):
    """Smallest eigenvalue and a unit eigenvector of each symmetric 3 x 3 matrix of a stack.

    The eigenvalues come from the trigonometric closed form of the characteristic cubic (Smith 1961), the
    eigenvector from the largest cross product of two rows of ``A - lambda_min I`` (both are orthogonal to the
    eigenvector), and the returned eigenvalue is the Rayleigh quotient of that eigenvector, which is accurate to
    the square of the eigenvector's error. Matrices whose two smallest eigenvalues (nearly) coincide, where the
    eigenvector is not determined by the matrix, go to ``numpy.linalg.eigh``.

    Parameters
    ----------
    matrices : (m, 3, 3) array
        Symmetric, finite (ValueError otherwise); scatter or covariance matrices in any units.

    Returns
    -------
    value : (m,) float64
        The smallest eigenvalue (for a scatter matrix: the spread along the plane's normal, units squared).
    vector : (m, 3) float64
        Its unit eigenvector (the sign arbitrary, as LAPACK's).
    """
    a = np.asarray(matrices, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ValueError(f"smallest_eigenpairs expects (m, 3, 3) matrices, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError("smallest_eigenpairs needs finite matrices (NaN or inf among them)")
    m = len(a)
    value, vector = np.empty(m), np.empty((m, 3))
    if m == 0:
        return value, vector
    a00, a11, a22 = a[:, 0, 0], a[:, 1, 1], a[:, 2, 2]
    a01, a02, a12 = a[:, 0, 1], a[:, 0, 2], a[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    d0, d1, d2 = a00 - q, a11 - q, a22 - q
    off = a01 * a01 + a02 * a02 + a12 * a12
    p = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    b00, b11, b22, b01, b02, b12 = d0 / safe, d1 / safe, d2 / safe, a01 / safe, a02 / safe, a12 / safe
    half_det = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    phi = np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    # rows of A - smallest I; the eigenvector is orthogonal to each, so to the cross product of any two (written
    # out by component: numpy's cross and stacks cost more than the arithmetic)
    e00, e11, e22 = a00 - smallest, a11 - smallest, a22 - smallest
    c01 = (a01 * a12 - a02 * e11, a02 * a01 - e00 * a12, e00 * e11 - a01 * a01)  # row 0 x row 1
    c02 = (a01 * e22 - a02 * a12, a02 * a02 - e00 * e22, e00 * a12 - a01 * a02)  # row 0 x row 2
    c12 = (e11 * e22 - a12 * a12, a12 * a02 - a01 * e22, a01 * a12 - e11 * a02)  # row 1 x row 2
    n01 = c01[0] * c01[0] + c01[1] * c01[1] + c01[2] * c01[2]
    n02 = c02[0] * c02[0] + c02[1] * c02[1] + c02[2] * c02[2]
    n12 = c12[0] * c12[0] + c12[1] * c12[1] + c12[2] * c12[2]
    first = (n01 >= n02) & (n01 >= n12)
    second = ~first & (n02 >= n12)
    best_norm = np.where(first, n01, np.where(second, n02, n12))
    x, y, z = (np.where(first, u, np.where(second, v, w)) for u, v, w in zip(c01, c02, c12))
    gap = largest - smallest
    good = (p > 0) & (best_norm > (_CROSS_FRACTION * gap * gap) ** 2)
    scale = 1.0 / np.sqrt(np.where(good, best_norm, 1.0))
    x, y, z = x * scale, y * scale, z * scale
    vector[:, 0], vector[:, 1], vector[:, 2] = x, y, z
    value[:] = (a00 * x * x + a11 * y * y + a22 * z * z + 2.0 * (a01 * x * y + a02 * x * z + a12 * y * z))
    bad = ~good
    if bad.any():
        vals, vecs = np.linalg.eigh(a[bad])
        value[bad], vector[bad] = vals[:, 0], vecs[:, :, 0]
    return value, vector
