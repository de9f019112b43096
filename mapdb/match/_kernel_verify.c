/* The per-image glue around the decision, compiled: a refined hypothesis's error model (refine.candidates,
 * evidence.relief.fit_with_relief) and the rivals' repeats (rivals._shifted).
 *
 * Each function replaces a chain of small numpy calls whose arithmetic it reproduces step by step (numpy's
 * pairwise sums, complex products, quotients and array absolute values from _kernel_numpy.c; libm's pow and
 * hypot where numpy's scalar arithmetic takes them), so that the same inputs give the same bits.  The numpy code
 * replaced is kept verbatim in tests/test_kernel_verify.py as the reference.
 */
#include "_kernel.h"

#include <math.h>
#include <stdint.h>

/* One row's error model over its inliers (compacted, in order): the residual sigma sqrt(sum d^2 / max(2k - 4, 1))
 * and the prediction variance factor 1/k + |mu|^2 / sum |z - mu|^2 at the image centre (the numpy code took
 * the mean and the spread of the array z[inlier] with weights of one, the last terms on numpy scalars). */
static void verify_row_errors(const double *z, const double *dist, const unsigned char *inlier, Py_ssize_t n,
                              double *tmp, double *ctmp, double *sigma, double *variance)
{
    Py_ssize_t k = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (inlier[i]) {
            tmp[k] = dist[i] * dist[i];
            /* w * src: the weight 1 promoted to a complex number, numpy's complex product */
            cmul(1.0, 0.0, z[2 * i], z[2 * i + 1], &ctmp[2 * k], &ctmp[2 * k + 1]);
            k++;
        }
    }
    Py_ssize_t dof = 2 * k - 4 > 1 ? 2 * k - 4 : 1;
    *sigma = sqrt(pw_sum(tmp, k) / (double)dof);
    double count = (double)k, sr, si, mr, mi;
    cpw_sum(ctmp, k, &sr, &si);
    cdiv(sr, si, count, 0.0, &mr, &mi);  /* a complex scalar over a float one: numpy's complex quotient */
    Py_ssize_t j = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (inlier[i]) {
            double r = cabs_np(z[2 * i] - mr, z[2 * i + 1] - mi);
            tmp[j++] = r * r;  /* an array's ** 2 is numpy's square */
        }
    }
    double spread = pw_sum(tmp, k);
    double at = pow(cabs_np(0.0 - mr, 0.0 - mi), 2.0);  /* a numpy scalar's ** 2 is pow */
    *variance = 1.0 / count + at / spread;
}

static PyObject *verify_errors(PyObject *self, PyObject *args)
{
    PyObject *oz, *odist, *oinl, *osig, *ovar;
    Arr a[5] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOO:verify_errors", &oz, &odist, &oinl, &osig, &ovar)) {
        return NULL;
    }
    if (arr_take(oz, &a[0], "z", 'Z', 1, 0, 0) || arr_take(odist, &a[1], "dist", 'd', 2, 0, 0)
        || arr_take(oinl, &a[2], "inlier", '?', 2, 0, 0) || arr_take(osig, &a[3], "sigma", 'd', 1, 1, 0)
        || arr_take(ovar, &a[4], "variance", 'd', 1, 1, 0)) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), h = arr_dim(&a[1], 0);
    if (arr_check_shape(&a[1], "dist", h, n) || arr_check_shape(&a[2], "inlier", h, n)
        || arr_check_shape(&a[3], "sigma", h, 0) || arr_check_shape(&a[4], "variance", h, 0)) {
        arr_release(a, 5);
        return NULL;
    }
    double *tmp = PyMem_Malloc(sizeof(double) * (size_t)(3 * n + 2));
    if (tmp == NULL) {
        arr_release(a, 5);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t r = 0; r < h; r++) {
        verify_row_errors(D(a[0]), D(a[1]) + r * n, B(a[2]) + r * n, n, tmp, tmp + n, D(a[3]) + r, D(a[4]) + r);
    }
    PyMem_Free(tmp);
    arr_release(a, 5);
    Py_RETURN_NONE;
}

/* The first index of the smallest of x[0 .. m) (numpy's argmin: the first NaN if any). */
static Py_ssize_t verify_argmin(const double *x, Py_ssize_t m)
{
    Py_ssize_t best = 0;
    for (Py_ssize_t i = 0; i < m; i++) {
        if (isnan(x[i])) {
            return i;
        }
        if (x[i] < x[best]) {
            best = i;
        }
    }
    return best;
}

/* rivals._shifted's arithmetic: the inliers' map points p (m,) of labels lab, the winner's pose (a0, b0).  Writes
 * the moved poses into hit_a, hit_b (room for m * m) and returns their count. */
static Py_ssize_t verify_shift_poses(const double *p, const int64_t *lab, Py_ssize_t m, double a0r, double a0i,
                                     double b0r, double b0i, double tolerance, double *tmp, double *ha, double *hb)
{
    for (Py_ssize_t i = 0; i < m; i++) {
        tmp[i] = cabs_np(p[2 * i] - b0r, p[2 * i + 1] - b0i);
    }
    Py_ssize_t i0 = verify_argmin(tmp, m);
    for (Py_ssize_t i = 0; i < m; i++) {
        tmp[i] = cabs_np(p[2 * i] - p[2 * i0], p[2 * i + 1] - p[2 * i0 + 1]);
        tmp[i] = tmp[i] == 0.0 ? INFINITY : tmp[i];
    }
    Py_ssize_t i1 = verify_argmin(tmp, m), count = 0;
    double base_r = p[2 * i1] - p[2 * i0], base_i = p[2 * i1 + 1] - p[2 * i0 + 1];
    double reach = hypot(base_r, base_i);  /* abs() of a numpy complex scalar */
    double off_r = b0r - p[2 * i0], off_i = b0i - p[2 * i0 + 1];
    for (Py_ssize_t j = 0; j < m; j++) {
        if (lab[j] != lab[i0]) {
            continue;
        }
        for (Py_ssize_t k = 0; k < m; k++) {
            double sr = p[2 * k] - p[2 * j], si = p[2 * k + 1] - p[2 * j + 1];
            if (!(fabs(cabs_np(sr, si) - reach) <= tolerance) || lab[k] != lab[i1]) {
                continue;
            }
            double tr, ti, mr, mi;
            cdiv(sr, si, base_r, base_i, &tr, &ti);
            cmul(tr, ti, a0r, a0i, &ha[2 * count], &ha[2 * count + 1]);
            cmul(tr, ti, off_r, off_i, &mr, &mi);
            hb[2 * count] = mr + p[2 * j];
            hb[2 * count + 1] = mi + p[2 * j + 1];
            count++;
        }
    }
    return count;
}

static PyObject *verify_shifted(PyObject *self, PyObject *args)
{
    PyObject *op, *olab, *oha, *ohb;
    Py_complex a0, b0;
    double tolerance;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OODDdOO:verify_shifted", &op, &olab, &a0, &b0, &tolerance, &oha, &ohb)) {
        return NULL;
    }
    if (arr_take(op, &a[0], "p", 'Z', 1, 0, 0) || arr_take(olab, &a[1], "lab", 'q', 1, 0, 0)
        || arr_take(oha, &a[2], "hit_a", 'Z', 1, 1, 0) || arr_take(ohb, &a[3], "hit_b", 'Z', 1, 1, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    Py_ssize_t m = arr_dim(&a[0], 0);
    if (arr_check_shape(&a[1], "lab", m, 0) || arr_check_shape(&a[2], "hit_a", m * m, 0)
        || arr_check_shape(&a[3], "hit_b", m * m, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    if (m < 1) {
        arr_release(a, 4);
        PyErr_SetString(PyExc_ValueError, "p must hold at least one point");
        return NULL;
    }
    double *tmp = PyMem_Malloc(sizeof(double) * (size_t)m);
    if (tmp == NULL) {
        arr_release(a, 4);
        return PyErr_NoMemory();
    }
    Py_ssize_t count = verify_shift_poses(D(a[0]), Q(a[1]), m, a0.real, a0.imag, b0.real, b0.imag, tolerance, tmp,
                                          D(a[2]), D(a[3]));
    PyMem_Free(tmp);
    arr_release(a, 4);
    return PyLong_FromSsize_t(count);
}

PyMethodDef verify_methods[] = {
    {"verify_errors", verify_errors, METH_VARARGS,
     "verify_errors(z, dist, inlier, sigma, variance): each row's residual sigma and prediction variance factor "
     "over its inliers."},
    {"verify_shifted", verify_shifted, METH_VARARGS,
     "verify_shifted(p, lab, a0, b0, tolerance, hit_a, hit_b): the winner's pose moved by the map's repeats among "
     "its inliers' points; returns how many were written."},
    {NULL, NULL, 0, NULL},
};
