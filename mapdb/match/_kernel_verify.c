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

/* ------------------------------------------------------------------ the screen, fused */

/* u of every screened object: each hypothesis's projection a z + b of its objects (numpy's complex product and
 * sum), the nearest map object of the object's label, kept when within reach (ObjectIndex.nearest under the
 * region's densities), and u = (density pi) (d d) (inf when none).  The search is bounded per point by its own
 * label's reach (a hair over it, r^2 (1 + 1e-9): every distance whose square root is within the reach lies below),
 * and an answer kept when it passes the tests ObjectIndex.nearest made with one bound for all (the largest
 * reach asked, at most half the label gap): the nearest below the smaller bound is the nearest below the larger
 * one whenever either passes, so the answers are the same with less of the tree walked. */
static void verify_screen_u(ObjectsTree *t, const double *a, const double *b, const double *z, const int64_t *obj,
                            const int64_t *lab, const double *reach, const double *density, double half_gap,
                            Py_ssize_t h, Py_ssize_t k, double *u)
{
    double rmax = -INFINITY;
    for (Py_ssize_t j = 0; j < h * k; j++) {
        double r = reach[lab[obj[j]]];
        rmax = r > rmax ? r : rmax;
    }
    double bound = half_gap < rmax ? half_gap : rmax, bound2 = bound * bound;
    for (Py_ssize_t r = 0; r < h; r++) {
        for (Py_ssize_t c = 0; c < k; c++) {
            int64_t o = obj[r * k + c], l = lab[o];
            double wr, wi, d2, reach_l = reach[l], prune2 = reach_l * reach_l * (1.0 + 1e-9);
            cmul(a[2 * r], a[2 * r + 1], z[2 * o], z[2 * o + 1], &wr, &wi);
            wr += b[2 * r];
            wi += b[2 * r + 1];
            int64_t i = objects_nearest1(t, l, wr, wi, prune2 < bound2 ? prune2 : bound2, &d2);
            double d = i >= 0 && d2 < bound2 ? sqrt(d2) : INFINITY;
            d = d <= reach_l ? d : INFINITY;
            u[r * k + c] = (density[l] * M_PI) * (d * d);
        }
    }
}

/* The arrays' indices in range: 0, or -1 with ValueError set. */
static int verify_screen_check(const int64_t *obj, Py_ssize_t hk, Py_ssize_t n, const int64_t *lab, Py_ssize_t nl)
{
    for (Py_ssize_t j = 0; j < hk; j++) {
        if (obj[j] < 0 || obj[j] >= n) {
            PyErr_Format(PyExc_ValueError, "objects holds %lld, outside 0..%zd", (long long)obj[j], n - 1);
            return -1;
        }
    }
    for (Py_ssize_t j = 0; j < n; j++) {
        if (lab[j] < 0 || lab[j] >= nl) {
            PyErr_Format(PyExc_ValueError, "img_label holds %lld, outside 0..%zd", (long long)lab[j], nl - 1);
            return -1;
        }
    }
    return 0;
}

static PyObject *verify_screen(PyObject *self, PyObject *args)
{
    PyObject *o[5], *oa, *ob, *oz, *oobj, *olab, *oreach, *odens, *onfa;
    double half_gap, offset, floor_;
    Py_ssize_t ns;
    Arr a[13] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOdnddO:verify_screen", &o[0], &o[1], &o[2], &o[3], &o[4], &oa, &ob, &oz,
                          &oobj, &olab, &oreach, &odens, &half_gap, &ns, &offset, &floor_, &onfa)) {
        return NULL;
    }
    ObjectsTree t;
    if (objects_take_tree(o, a, &t) < 0 || arr_take(oa, &a[5], "a", 'Z', 1, 0, 0) || arr_take(ob, &a[6], "b", 'Z', 1, 0, 0)
        || arr_take(oz, &a[7], "z", 'Z', 1, 0, 0) || arr_take(oobj, &a[8], "objects", 'q', 2, 0, 0)
        || arr_take(olab, &a[9], "img_label", 'q', 1, 0, 0) || arr_take(oreach, &a[10], "reach", 'd', 1, 0, 0)
        || arr_take(odens, &a[11], "density", 'd', 1, 0, 0) || arr_take(onfa, &a[12], "nfa", 'd', 1, 1, 0)) {
        arr_release(a, 13);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[5], 0), k = arr_dim(&a[8], 1), n = arr_dim(&a[7], 0), nl = arr_dim(&a[10], 0);
    if (arr_check_shape(&a[6], "b", h, 0) || arr_check_shape(&a[8], "objects", h, k)
        || arr_check_shape(&a[9], "img_label", n, 0) || arr_check_shape(&a[11], "density", nl, 0)
        || arr_check_shape(&a[12], "nfa", h, 0) || verify_screen_check(Q(a[8]), h * k, n, Q(a[9]), nl)) {
        arr_release(a, 13);
        return NULL;
    }
    if (ns < 0 || ns >= k) {
        arr_release(a, 13);
        PyErr_Format(PyExc_ValueError, "n_sample must be in 0..%zd, got %zd", k - 1, ns);
        return NULL;
    }
    double *u = PyMem_Malloc(sizeof(double) * (size_t)(h * k + 1));
    int64_t *best = PyMem_Malloc(sizeof(int64_t) * (size_t)(h + 1));
    if (u == NULL || best == NULL) {
        PyMem_Free(u);
        PyMem_Free(best);
        arr_release(a, 13);
        return PyErr_NoMemory();
    }
    verify_screen_u(&t, D(a[5]), D(a[6]), D(a[7]), Q(a[8]), Q(a[9]), D(a[10]), D(a[11]), half_gap, h, k, u);
    int failed = t.bad ? 0 : nfa_rows(u, NULL, NULL, h, k, ns, offset, floor_, D(a[12]), best);
    PyMem_Free(u);
    PyMem_Free(best);
    arr_release(a, 13);
    return failed ? NULL : objects_checked(&t);
}

PyMethodDef verify_methods[] = {
    {"verify_errors", verify_errors, METH_VARARGS,
     "verify_errors(z, dist, inlier, sigma, variance): each row's residual sigma and prediction variance factor "
     "over its inliers."},
    {"verify_shifted", verify_shifted, METH_VARARGS,
     "verify_shifted(p, lab, a0, b0, tolerance, hit_a, hit_b): the winner's pose moved by the map's repeats among "
     "its inliers' points; returns how many were written."},
    {"verify_screen", verify_screen, METH_VARARGS,
     "verify_screen(pts, pid, box, node, root, a, b, z, objects, img_label, reach, density, half_gap, n_sample, "
     "offset, floor, nfa): the screen's log10 NFA a hypothesis, projections, nearest objects and curve fused."},
    {NULL, NULL, 0, NULL},
};
