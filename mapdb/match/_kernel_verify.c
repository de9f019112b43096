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
    double hi2 = (reach + tolerance) * (reach + tolerance) * (1.0 + 1e-9);
    double lo2 = reach > tolerance ? (reach - tolerance) * (reach - tolerance) * (1.0 - 1e-9) : -1.0;
    for (Py_ssize_t j = 0; j < m; j++) {
        if (lab[j] != lab[i0]) {
            continue;
        }
        for (Py_ssize_t k = 0; k < m; k++) {
            /* the label first, then the squared distance against bounds a hair wider than the test's (a pair
             * outside them fails it: only those near it, and NaN, take the exact test's square root) */
            if (lab[k] != lab[i1]) {
                continue;
            }
            double sr = p[2 * k] - p[2 * j], si = p[2 * k + 1] - p[2 * j + 1], d2 = sr * sr + si * si;
            if (d2 > hi2 || d2 < lo2 || !(fabs(cabs_np(sr, si) - reach) <= tolerance)) {
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

/* ------------------------------------------------------------------ the decision on points, fused */

/* A decision's inputs, read from the neighbours of the projections (ObjectIndex.neighbours: K a point). */
typedef struct {
    const double *nd, *zmap, *ex, *z, *reach, *density, *kd_floor;
    const int64_t *ni, *ids, *lab, *counts;
    Py_ssize_t h, n, k_near, k_first, nz, ne, q, n_labels, local;
    int per_row;  /* density holds a row a hypothesis (else one row for all) */
} VerifyDecision;

/* u of object i under hypothesis r: the first of its k_first neighbours within its label's reach and not at one of
 * the hypothesis's own map points (ObjectIndex.nearest), its label's density (the larger of it and the
 * local_neighbours-th neighbour's, ObjectIndex.knn_density, when local_neighbours > 0), (lam pi) (d d). */
static double verify_decision_u(const VerifyDecision *v, Py_ssize_t r, Py_ssize_t i)
{
    Py_ssize_t q = r * v->n + i;
    int64_t l = v->lab[i], oi;
    double dist;
    first_allowed_rows(v->nd + q * v->k_near, v->ni + q * v->k_near, &v->reach[l], v->zmap, v->nz,
                       v->ex + 2 * r * v->ne, v->ne, 1, NULL, 1, v->k_first, &dist, &oi);
    double lam = v->density[(v->per_row ? r : 0) * v->n_labels + l];
    if (v->local > 0) {
        int64_t kk = v->counts[l] < v->local ? v->counts[l] : v->local;
        double kd = *v->kd_floor;
        if (kk > 0) {
            double d = v->nd[q * v->k_near + kk - 1];
            d = (isnan(d) || d >= 1e-3) ? d : 1e-3;
            kd = (double)(kk - 1 > 1 ? kk - 1 : 1) / (M_PI * (d * d));
        }
        lam = (isnan(lam) || lam >= kd) ? lam : kd;  /* numpy's maximum: NaN kept */
    }
    return (lam * M_PI) * (dist * dist);
}

/* Shapes of the arrays, indices in range: 0, or -1 with ValueError set. */
static int verify_decision_check(const VerifyDecision *v, Py_ssize_t rows_density)
{
    if (v->k_first < 1 || v->k_first > v->k_near || v->local > v->k_near || v->local < 0 || v->nz < 1) {
        PyErr_SetString(PyExc_ValueError, "need 1 <= k_first <= K, 0 <= local_neighbours <= K and a map object");
        return -1;
    }
    if (rows_density != 1 && rows_density != v->h) {
        PyErr_Format(PyExc_ValueError, "density must have 1 or %zd rows, got %zd", v->h, rows_density);
        return -1;
    }
    for (Py_ssize_t j = 0; j < v->h * v->q; j++) {
        if (v->ids[j] < 0 || v->ids[j] >= v->n) {
            PyErr_Format(PyExc_ValueError, "img_ids must lie in 0..%zd", v->n - 1);
            return -1;
        }
    }
    for (Py_ssize_t j = 0; j < v->n; j++) {
        if (v->lab[j] < 0 || v->lab[j] >= v->n_labels) {
            PyErr_Format(PyExc_ValueError, "img_label holds %lld, outside 0..%zd", (long long)v->lab[j],
                         v->n_labels - 1);
            return -1;
        }
    }
    for (Py_ssize_t j = 0; j < v->h * v->n * v->k_near; j++) {
        if (v->ni[j] < 0) {
            PyErr_SetString(PyExc_ValueError, "near_i must hold no negative index");
            return -1;
        }
    }
    return 0;
}

/* Every row's u, shapes and sample mask, then the curve: 0, or -1 with MemoryError set. */
static int verify_decision_rows(const VerifyDecision *v, Py_ssize_t ns, double offset, double floor_, double *nfa)
{
    Py_ssize_t hn = v->h * v->n;
    double *u = PyMem_Malloc(sizeof(double) * (size_t)(2 * hn + 2 * v->q + 1));
    unsigned char *sample = PyMem_Malloc((size_t)hn + 1);
    int64_t *best = PyMem_Malloc(sizeof(int64_t) * (size_t)(v->h + 1));
    if (u == NULL || sample == NULL || best == NULL) {
        PyMem_Free(u);
        PyMem_Free(sample);
        PyMem_Free(best);
        PyErr_NoMemory();
        return -1;
    }
    double *shape = u + hn, *buf = shape + hn;
    for (Py_ssize_t r = 0; r < v->h; r++) {
        for (Py_ssize_t i = 0; i < v->n; i++) {
            u[r * v->n + i] = verify_decision_u(v, r, i);
        }
        quad_row(v->z, v->n, v->ids + r * v->q, v->q, buf, shape + r * v->n, sample + r * v->n);
    }
    int failed = nfa_rows(u, shape, sample, v->h, v->n, ns, offset, floor_, nfa, best);
    for (Py_ssize_t r = 0; !failed && r < v->h; r++) {
        nfa[r] = nfa[r] + 0.0;  /* decision_nfa's nfa + from_sample (zeros): -0.0 becomes 0.0 */
    }
    PyMem_Free(u);
    PyMem_Free(sample);
    PyMem_Free(best);
    return failed;
}

static PyObject *verify_decision(PyObject *self, PyObject *args)
{
    static const char *names[11] = {"near_d", "near_i", "map_z", "exclude", "img_ids", "z", "img_label", "reach",
                                    "density", "counts", "nfa"};
    static const char kinds[11] = {'d', 'q', 'Z', 'Z', 'q', 'Z', 'q', 'd', 'd', 'q', 'd'};
    static const int dims[11] = {2, 2, 1, 2, 2, 1, 1, 1, 2, 1, 1};
    PyObject *o[11];
    Py_ssize_t k_first, local, ns;
    double kd_floor, offset, floor_;
    Arr a[11] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOnOOOOOOOOndnddO:verify_decision", &o[0], &o[1], &k_first, &o[2], &o[3], &o[4],
                          &o[5], &o[6], &o[7], &o[8], &o[9], &local, &kd_floor, &ns, &offset, &floor_, &o[10])) {
        return NULL;
    }
    for (int j = 0; j < 11; j++) {
        if (arr_take(o[j], &a[j], names[j], kinds[j], dims[j], j == 10, 0)) {
            arr_release(a, 11);
            return NULL;
        }
    }
    VerifyDecision v = {D(a[0]), D(a[2]), D(a[3]), D(a[5]), D(a[7]), D(a[8]), &kd_floor, Q(a[1]), Q(a[4]), Q(a[6]),
                        Q(a[9]), arr_dim(&a[4], 0), arr_dim(&a[5], 0), arr_dim(&a[0], 1), k_first, arr_dim(&a[2], 0),
                        arr_dim(&a[3], 1), arr_dim(&a[4], 1), arr_dim(&a[7], 0), local, arr_dim(&a[8], 0) > 1};
    if (arr_check_shape(&a[0], "near_d", v.h * v.n, v.k_near) || arr_check_shape(&a[1], "near_i", v.h * v.n, v.k_near)
        || arr_check_shape(&a[3], "exclude", v.h, v.ne) || arr_check_shape(&a[6], "img_label", v.n, 0)
        || arr_check_shape(&a[8], "density", arr_dim(&a[8], 0), v.n_labels)
        || arr_check_shape(&a[9], "counts", v.n_labels, 0) || arr_check_shape(&a[10], "nfa", v.h, 0)
        || verify_decision_check(&v, arr_dim(&a[8], 0))) {
        arr_release(a, 11);
        return NULL;
    }
    if (ns < 0 || ns >= v.n) {
        arr_release(a, 11);
        PyErr_Format(PyExc_ValueError, "n_sample must be in 0..%zd, got %zd", v.n - 1, ns);
        return NULL;
    }
    int failed = verify_decision_rows(&v, ns, offset, floor_, D(a[10]));
    arr_release(a, 11);
    if (failed) {
        return NULL;
    }
    Py_RETURN_NONE;
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
    {"verify_decision", verify_decision, METH_VARARGS,
     "verify_decision(near_d, near_i, k_first, map_z, exclude, img_ids, z, img_label, reach, density, counts, "
     "local_neighbours, kd_floor, n_sample, offset, floor, nfa): decision_nfa on point residuals from the "
     "projections' neighbours, fused."},
    {NULL, NULL, 0, NULL},
};
