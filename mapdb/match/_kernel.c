/* mapdb's compiled kernel: the matcher's per-image arithmetic, on the CPython C API alone.
 *
 * Arrays come in through the buffer protocol (numpy arrays are buffers), C-contiguous, of the exact format each
 * function names; outputs are written into arrays the Python caller allocated.  Building needs a C compiler and
 * Python's headers, nothing else (no numpy headers, no Cython).  The Python wrappers in mapdb/match/ check
 * dtypes and shapes and make arrays contiguous; every function here checks formats, dimensions and sizes again
 * and raises TypeError or ValueError rather than read past a buffer.
 *
 * Where the numpy code this replaces summed, it summed pairwise (numpy's pairwise_sum, reproduced in
 * _kernel_numpy.c's pw_sum and cpw_sum with the same blocks and order), and complex products and quotients
 * follow numpy's formulas (cmul, cdiv: Smith's division; cabs_np), so that the same inputs give the same bits;
 * the exceptions are expm1 and log10, which numpy may take from SIMD libraries (SVML on AVX-512 machines) that
 * differ from the C library's by an ulp.  Compiled with -ffp-contract=off: no fused multiply-adds but the
 * explicit ones.
 *
 * This file holds the module and the refinement's, the fit's, the first allowed neighbour's and the tolerance
 * shapes' arithmetic; the other files one concept each (docs/architecture.md lists them; _kernel.h declares what
 * they share).
 */
#include "_kernel.h"

#include <math.h>
#include <float.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------ refinement */

static double row_sigma(const double *dist, const unsigned char *inlier, Py_ssize_t n, double *tmp)
{
    Py_ssize_t k = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        k += inlier[i] != 0;
        tmp[i] = inlier[i] ? dist[i] * dist[i] : 0.0;
    }
    Py_ssize_t dof = 2 * k - 4 > 1 ? 2 * k - 4 : 1;
    return sqrt(pw_sum(tmp, n) / (double)dof);
}

/* Of the inliers matched to one map object, only the closest stays (ties: the first). */
static void row_first_per_map_object(const int64_t *mid, const double *dist, const unsigned char *inlier,
                                     Py_ssize_t n, unsigned char *keep)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        keep[i] = 1;
        if (!inlier[i]) {
            continue;
        }
        for (Py_ssize_t j = 0; j < n; j++) {
            if (j != i && inlier[j] && mid[j] == mid[i]
                && (np_less(dist[j], dist[i]) || (!np_less(dist[i], dist[j]) && j < i))) {
                keep[i] = 0;
                break;
            }
        }
    }
}

void row_inliers(const double *u, const double *dist, const int64_t *mid, int64_t k_best, double gate,
                        Py_ssize_t n, double *x, unsigned char *keep, unsigned char *inlier)
{
    memcpy(x, u, sizeof(double) * (size_t)n);
    sort_values(x, n);
    int64_t at = k_best - 1 < 0 ? 0 : (k_best - 1 > n - 1 ? n - 1 : k_best - 1);
    double cut = x[at];
    for (Py_ssize_t i = 0; i < n; i++) {
        inlier[i] = u[i] <= cut && isfinite(dist[i]);
    }
    double reach = gate * row_sigma(dist, inlier, n, x);
    for (Py_ssize_t i = 0; i < n; i++) {
        inlier[i] |= dist[i] <= reach && isfinite(dist[i]);
    }
    row_first_per_map_object(mid, dist, inlier, n, keep);
    for (Py_ssize_t i = 0; i < n; i++) {
        inlier[i] &= keep[i];
    }
}

static PyObject *refine_inliers(PyObject *self, PyObject *args)
{
    PyObject *ou, *odist, *omid, *okb, *oout;
    double gate;
    Arr a[5] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOdO:refine_inliers", &ou, &odist, &omid, &okb, &gate, &oout)) {
        return NULL;
    }
    if (arr_take(ou, &a[0], "u", 'd', 2, 0, 0) || arr_take(odist, &a[1], "dist", 'd', 2, 0, 0)
        || arr_take(omid, &a[2], "mid", 'q', 2, 0, 0) || arr_take(okb, &a[3], "k_best", 'q', 1, 0, 0)
        || arr_take(oout, &a[4], "inlier", '?', 2, 1, 0)) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), n = arr_dim(&a[0], 1);
    if (n < 1) {
        PyErr_SetString(PyExc_ValueError, "u must have at least one column");
    } else if (!arr_check_shape(&a[1], "dist", h, n) && !arr_check_shape(&a[2], "mid", h, n)
               && !arr_check_shape(&a[3], "k_best", h, 0)) {
        arr_check_shape(&a[4], "inlier", h, n);
    }
    if (PyErr_Occurred()) {
        arr_release(a, 5);
        return NULL;
    }
    double *x = PyMem_Malloc(sizeof(double) * (size_t)n);
    unsigned char *keep = PyMem_Malloc((size_t)n);
    if (x == NULL || keep == NULL) {
        PyMem_Free(x);
        PyMem_Free(keep);
        arr_release(a, 5);
        return PyErr_NoMemory();
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t r = 0; r < h; r++) {
        row_inliers(D(a[0]) + r * n, D(a[1]) + r * n, Q(a[2]) + r * n, Q(a[3])[r], gate, n, x, keep,
                    B(a[4]) + r * n);
    }
    Py_END_ALLOW_THREADS
    PyMem_Free(x);
    PyMem_Free(keep);
    arr_release(a, 5);
    Py_RETURN_NONE;
}

static PyObject *residual_sigmas(PyObject *self, PyObject *args)
{
    PyObject *odist, *oinl, *oout;
    Arr a[3] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOO:residual_sigmas", &odist, &oinl, &oout)) {
        return NULL;
    }
    if (arr_take(odist, &a[0], "dist", 'd', 2, 0, 0) || arr_take(oinl, &a[1], "inlier", '?', 2, 0, 0)
        || arr_take(oout, &a[2], "out", 'd', 1, 1, 0)) {
        arr_release(a, 3);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), n = arr_dim(&a[0], 1);
    if (arr_check_shape(&a[1], "inlier", h, n) || arr_check_shape(&a[2], "out", h, 0)) {
        arr_release(a, 3);
        return NULL;
    }
    double *x = PyMem_Malloc(sizeof(double) * (size_t)(n + 1));
    if (x == NULL) {
        arr_release(a, 3);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t r = 0; r < h; r++) {
        D(a[2])[r] = row_sigma(D(a[0]) + r * n, B(a[1]) + r * n, n, x);
    }
    PyMem_Free(x);
    arr_release(a, 3);
    Py_RETURN_NONE;
}

static PyObject *first_per_map_object(PyObject *self, PyObject *args)
{
    PyObject *omid, *odist, *oinl, *oout;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOO:first_per_map_object", &omid, &odist, &oinl, &oout)) {
        return NULL;
    }
    if (arr_take(omid, &a[0], "mid", 'q', 2, 0, 0) || arr_take(odist, &a[1], "dist", 'd', 2, 0, 0)
        || arr_take(oinl, &a[2], "inlier", '?', 2, 0, 0) || arr_take(oout, &a[3], "keep", '?', 2, 1, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), n = arr_dim(&a[0], 1);
    if (arr_check_shape(&a[1], "dist", h, n) || arr_check_shape(&a[2], "inlier", h, n) || arr_check_shape(&a[3], "keep", h, n)) {
        arr_release(a, 4);
        return NULL;
    }
    for (Py_ssize_t r = 0; r < h; r++) {
        row_first_per_map_object(Q(a[0]) + r * n, D(a[1]) + r * n, B(a[2]) + r * n, n, B(a[3]) + r * n);
    }
    arr_release(a, 4);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ similarity fit */

/* One set: numpy's fit_similarity_complex step by step (w is real, cast to w + 0j where numpy casts it). */
void fit_row(const double *src, const double *dst, const double *w, Py_ssize_t k, double *buf, double *out)
{
    double *c = buf;          /* k complex */
    double *re = buf + 2 * k; /* k real */
    double wsum = pw_sum(w, k), sr, si, dr, di, mur, mui, mdr, mdi;
    for (Py_ssize_t i = 0; i < k; i++) {
        cmul(w[i], 0.0, src[2 * i], src[2 * i + 1], &c[2 * i], &c[2 * i + 1]);
    }
    cpw_sum(c, k, &sr, &si);
    cdiv(sr, si, wsum, 0.0, &mur, &mui);
    for (Py_ssize_t i = 0; i < k; i++) {
        cmul(w[i], 0.0, dst[2 * i], dst[2 * i + 1], &c[2 * i], &c[2 * i + 1]);
    }
    cpw_sum(c, k, &dr, &di);
    cdiv(dr, di, wsum, 0.0, &mdr, &mdi);
    for (Py_ssize_t i = 0; i < k; i++) {
        double s_r = src[2 * i] - mur, s_i = src[2 * i + 1] - mui;
        double d_r = dst[2 * i] - mdr, d_i = dst[2 * i + 1] - mdi, t_r, t_i;
        re[i] = w[i] * (s_r * s_r + s_i * s_i);
        cmul(w[i], 0.0, s_r, -s_i, &t_r, &t_i);
        cmul(t_r, t_i, d_r, d_i, &c[2 * i], &c[2 * i + 1]);
    }
    double norm = pw_sum(re, k), nr, ni, ar, ai, pr, pi;
    cpw_sum(c, k, &nr, &ni);
    cdiv(nr, ni, norm > 0 ? norm : NAN, 0.0, &ar, &ai);
    cmul(ar, ai, mur, mui, &pr, &pi);
    out[0] = ar;
    out[1] = ai;
    out[2] = mdr - pr;
    out[3] = mdi - pi;
}

static PyObject *fit_similarity(PyObject *self, PyObject *args)
{
    PyObject *osrc, *odst, *ow, *oa, *ob;
    Arr a[5] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOO:fit_similarity", &osrc, &odst, &ow, &oa, &ob)) {
        return NULL;
    }
    if (arr_take(osrc, &a[0], "src", 'Z', 2, 0, 0) || arr_take(odst, &a[1], "dst", 'Z', 2, 0, 0)
        || arr_take(ow, &a[2], "weights", 'd', 2, 0, 0) || arr_take(oa, &a[3], "a", 'Z', 1, 1, 0)
        || arr_take(ob, &a[4], "b", 'Z', 1, 1, 0)) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t m = arr_dim(&a[0], 0), k = arr_dim(&a[0], 1);
    if (arr_check_shape(&a[1], "dst", m, k) || arr_check_shape(&a[2], "weights", m, k) || arr_check_shape(&a[3], "a", m, 0)
        || arr_check_shape(&a[4], "b", m, 0)) {
        arr_release(a, 5);
        return NULL;
    }
    double *buf = PyMem_Malloc(sizeof(double) * (size_t)(3 * k + 1));
    if (buf == NULL) {
        arr_release(a, 5);
        return PyErr_NoMemory();
    }
    double *pa = D(a[3]), *pb = D(a[4]), out[4];
    for (Py_ssize_t r = 0; r < m; r++) {
        fit_row(D(a[0]) + 2 * r * k, D(a[1]) + 2 * r * k, D(a[2]) + r * k, k, buf, out);
        pa[2 * r] = out[0];
        pa[2 * r + 1] = out[1];
        pb[2 * r] = out[2];
        pb[2 * r + 1] = out[3];
    }
    PyMem_Free(buf);
    arr_release(a, 5);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ the first allowed neighbour */

void first_allowed_rows(const double *d, const int64_t *idx, const double *reach, const double *z,
                               Py_ssize_t nz, const double *ex, Py_ssize_t ne, Py_ssize_t repeat,
                               const unsigned char *allowed, Py_ssize_t m, Py_ssize_t k, double *od, int64_t *oi)
{
    for (Py_ssize_t q = 0; q < m; q++) {
        Py_ssize_t first = -1;
        const double *e = ex ? ex + 2 * (q / repeat) * ne : NULL;
        for (Py_ssize_t c = 0; c < k && first < 0; c++) {
            Py_ssize_t at = q * k + c;
            if (!(d[at] <= reach[q]) || (allowed && !allowed[at])) {
                continue;
            }
            int found = 1;
            int64_t j = idx[at] < nz - 1 ? idx[at] : nz - 1;
            for (Py_ssize_t x = 0; e && x < ne && found; x++) {
                found = !(cabs_np(z[2 * j] - e[2 * x], z[2 * j + 1] - e[2 * x + 1]) < 1e-6);
            }
            if (found) {
                first = c;
            }
        }
        od[q] = first < 0 ? INFINITY : d[q * k + first];
        oi[q] = first < 0 ? -1 : idx[q * k + first];
    }
}

static PyObject *first_allowed(PyObject *self, PyObject *args)
{
    PyObject *od, *oi, *oreach, *oz, *oex, *oallowed, *outd, *outi;
    Py_ssize_t repeat;
    Arr a[8] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOOnOOO:first_allowed", &od, &oi, &oreach, &oz, &oex, &repeat, &oallowed,
                          &outd, &outi)) {
        return NULL;
    }
    if (arr_take(od, &a[0], "d", 'd', 2, 0, 0) || arr_take(oi, &a[1], "i", 'q', 2, 0, 0)
        || arr_take(oreach, &a[2], "reach", 'd', 1, 0, 0) || arr_take(oz, &a[3], "z", 'Z', 1, 0, 0)
        || arr_take(oex, &a[4], "exclude", 'Z', 2, 0, 1) || arr_take(oallowed, &a[5], "allowed", '?', 2, 0, 1)
        || arr_take(outd, &a[6], "out_d", 'd', 1, 1, 0) || arr_take(outi, &a[7], "out_i", 'q', 1, 1, 0)) {
        arr_release(a, 8);
        return NULL;
    }
    Py_ssize_t m = arr_dim(&a[0], 0), k = arr_dim(&a[0], 1), nz = arr_dim(&a[3], 0);
    Py_ssize_t ne = a[4].held ? arr_dim(&a[4], 1) : 0;
    for (Py_ssize_t j = 0; j < arr_dim(&a[1], 0) * arr_dim(&a[1], 1) && !PyErr_Occurred(); j++) {
        if (Q(a[1])[j] < 0) {  /* a KD-tree's indices: 0 .. len(objects), the last for "none" */
            PyErr_SetString(PyExc_ValueError, "i must hold no negative index");
        }
    }
    if (PyErr_Occurred()) {
        arr_release(a, 8);
        return NULL;
    }
    if (repeat < 1 || nz < 1 || (a[4].held && arr_dim(&a[4], 0) * repeat < m)) {
        PyErr_SetString(PyExc_ValueError, "need repeat >= 1, a map object, and an exclude row per repeat rows");
    } else if (!arr_check_shape(&a[1], "i", m, k) && !arr_check_shape(&a[2], "reach", m, 0)
               && !arr_check_shape(&a[5], "allowed", m, k) && !arr_check_shape(&a[6], "out_d", m, 0)) {
        arr_check_shape(&a[7], "out_i", m, 0);
    }
    if (PyErr_Occurred()) {
        arr_release(a, 8);
        return NULL;
    }
    first_allowed_rows(D(a[0]), Q(a[1]), D(a[2]), D(a[3]), nz, a[4].held ? D(a[4]) : NULL, ne, repeat,
                       a[5].held ? B(a[5]) : NULL, m, k, D(a[6]), Q(a[7]));
    arr_release(a, 8);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ the decision's tolerance shapes */

/* One hypothesis: 1.25 + |z - mean|^2 / spread of its quad's image points, and the quad's objects marked. */
void quad_row(const double *z, Py_ssize_t n, const int64_t *ids, Py_ssize_t q, double *buf, double *shape,
                     unsigned char *sample)
{
    double mr, mi, sr, si;
    for (Py_ssize_t j = 0; j < q; j++) {
        buf[2 * j] = z[2 * ids[j]];
        buf[2 * j + 1] = z[2 * ids[j] + 1];
    }
    cpw_sum(buf, q, &sr, &si);
    cdiv(sr, si, (double)q, 0.0, &mr, &mi);
    for (Py_ssize_t j = 0; j < q; j++) {
        double r = cabs_np(buf[2 * j] - mr, buf[2 * j + 1] - mi);
        buf[j] = r * r;  /* buf[j] is read before it is written: j <= 2 j */
    }
    double spread = pw_sum(buf, q);
    for (Py_ssize_t i = 0; i < n; i++) {
        double r = cabs_np(z[2 * i] - mr, z[2 * i + 1] - mi);
        shape[i] = 1.25 + (r * r) / spread;
        sample[i] = 0;
    }
    for (Py_ssize_t j = 0; j < q; j++) {
        sample[ids[j]] = 1;
    }
}

static PyObject *quad_tolerance(PyObject *self, PyObject *args)
{
    PyObject *oz, *oids, *oshape, *osample;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOO:quad_tolerance", &oz, &oids, &oshape, &osample)) {
        return NULL;
    }
    if (arr_take(oz, &a[0], "z", 'Z', 1, 0, 0) || arr_take(oids, &a[1], "img_ids", 'q', 2, 0, 0)
        || arr_take(oshape, &a[2], "shape", 'd', 2, 1, 0) || arr_take(osample, &a[3], "sample", '?', 2, 1, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), h = arr_dim(&a[1], 0), q = arr_dim(&a[1], 1);
    for (Py_ssize_t j = 0; j < h * q && !PyErr_Occurred(); j++) {
        if (Q(a[1])[j] < 0 || Q(a[1])[j] >= n) {
            PyErr_Format(PyExc_ValueError, "img_ids must lie in 0..%zd", n - 1);
        }
    }
    if (PyErr_Occurred() || arr_check_shape(&a[2], "shape", h, n) || arr_check_shape(&a[3], "sample", h, n)) {
        arr_release(a, 4);
        return NULL;
    }
    double *buf = PyMem_Malloc(sizeof(double) * (size_t)(2 * q + 1));
    if (buf == NULL) {
        arr_release(a, 4);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t r = 0; r < h; r++) {
        quad_row(D(a[0]), n, Q(a[1]) + r * q, q, buf, D(a[2]) + r * n, B(a[3]) + r * n);
    }
    PyMem_Free(buf);
    arr_release(a, 4);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ module */

static PyMethodDef methods[] = {
    {"refine_inliers", refine_inliers, METH_VARARGS,
     "refine_inliers(u, dist, mid, k_best, gate_sigmas, inlier): the refinement's inlier mask."},
    {"residual_sigmas", residual_sigmas, METH_VARARGS,
     "residual_sigmas(dist, inlier, out): sqrt(sum r^2 / max(2k - 4, 1)) a row."},
    {"first_per_map_object", first_per_map_object, METH_VARARGS,
     "first_per_map_object(mid, dist, inlier, keep): the closest inlier a map object a row."},
    {"fit_similarity", fit_similarity, METH_VARARGS,
     "fit_similarity(src, dst, weights, a, b): weighted least-squares similarity a row."},
    {"first_allowed", first_allowed, METH_VARARGS,
     "first_allowed(d, i, reach, z, exclude, repeat, allowed, out_d, out_i): the nearest allowed neighbour."},
    {"quad_tolerance", quad_tolerance, METH_VARARGS,
     "quad_tolerance(z, img_ids, shape, sample): the decision's tolerance shapes and sample mask a hypothesis."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_kernel", "mapdb's compiled matcher kernel (see _kernel.c).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kernel(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) {
        return NULL;
    }
    if (PyModule_AddFunctions(m, nfa_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, objects_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, object_discs_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, verify_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, verify_refine_methods) < 0 || PyModule_AddFunctions(m, places_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, quads_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, quad_tree_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, image_quads_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, map_quads_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, stored_methods) < 0 || PyModule_AddFunctions(m, hits_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddFunctions(m, qdecode_methods) < 0 || PyModule_AddFunctions(m, qcheck_methods) < 0
        || PyModule_AddFunctions(m, screen_methods) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
