/* Distinct places among a round's hypotheses (refine.distinct): greedy non-maximum suppression, one call.
 *
 * The hypotheses are read in the order given (best first); one is kept when its place b lies farther than the
 * larger of the two separations from every place kept before it, until ``limit`` are kept.  The Python loop it
 * replaces compared Python complex numbers: |b_i - b_j| is their abs (the C library's hypot of the difference's
 * parts, inf when either part is infinite, NaN when either is NaN and none is infinite), and the larger separation
 * is Python's max(s_i, s_j) (s_j when s_j > s_i, else s_i: a NaN first stays, a NaN second is passed over), so the
 * same places are kept for any input.  A round's screen called that loop with 16 hypotheses and 4 places to keep:
 * 30 microseconds of Python calls an image for a few hundred floating point operations.
 */
#include "_kernel.h"

/* |z| of a Python complex z (complex_abs: hypot, with infinities before NaNs). */
static double places_abs(double re, double im)
{
    if (isinf(re) || isinf(im)) {
        return INFINITY;
    }
    if (isnan(re) || isnan(im)) {
        return NAN;
    }
    return hypot(re, im);
}

/* The kept rows of ``order`` (m of them, each in 0 .. h) written to out; how many. */
static Py_ssize_t places_keep(const double *b, const double *sep, const int64_t *order, Py_ssize_t m,
                              Py_ssize_t limit, int64_t *out)
{
    Py_ssize_t kept = 0;
    for (Py_ssize_t p = 0; p < m && kept < limit; p++) {
        int64_t i = order[p];
        int apart = 1;
        for (Py_ssize_t q = 0; q < kept && apart; q++) {
            int64_t j = out[q];
            double wider = sep[j] > sep[i] ? sep[j] : sep[i];  /* Python's max(sep[i], sep[j]) */
            apart = places_abs(b[2 * i] - b[2 * j], b[2 * i + 1] - b[2 * j + 1]) > wider;
        }
        if (apart) {
            out[kept++] = i;
        }
    }
    return kept;
}

static PyObject *places_distinct(PyObject *self, PyObject *args)
{
    PyObject *ob, *oorder, *osep, *oout;
    Py_ssize_t limit;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOnO:places_distinct", &ob, &oorder, &osep, &limit, &oout)) {
        return NULL;
    }
    if (arr_take(ob, &a[0], "b", 'Z', 1, 0, 0) || arr_take(oorder, &a[1], "order", 'q', 1, 0, 0)
        || arr_take(osep, &a[2], "separation", 'd', 1, 0, 0) || arr_take(oout, &a[3], "out", 'q', 1, 1, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), m = arr_dim(&a[1], 0);
    if (arr_check_shape(&a[2], "separation", h, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    if (limit < 0 || arr_dim(&a[3], 0) < (limit < m ? limit : m)) {
        PyErr_Format(PyExc_ValueError, "limit must be at least 0 and out hold min(limit, %zd) rows", m);
        arr_release(a, 4);
        return NULL;
    }
    for (Py_ssize_t p = 0; p < m; p++) {
        if (Q(a[1])[p] < 0 || Q(a[1])[p] >= h) {
            PyErr_Format(PyExc_ValueError, "order must hold indices in 0 .. %zd", h - 1);
            arr_release(a, 4);
            return NULL;
        }
    }
    Py_ssize_t kept = places_keep(D(a[0]), D(a[2]), Q(a[1]), m, limit, Q(a[3]));
    arr_release(a, 4);
    return PyLong_FromSsize_t(kept);
}

PyMethodDef places_methods[] = {
    {"places_distinct", places_distinct, METH_VARARGS,
     "places_distinct(b, order, separation, limit, out) -> kept: the rows of order (best first) whose place b lies "
     "farther than the larger separation from every row kept before, at most limit, written to out."},
    {NULL, NULL, 0, NULL},
};
