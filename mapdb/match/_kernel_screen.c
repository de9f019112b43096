/* The screen's neighbours of image objects (screen.screen_neighbours): each image object's k nearest image objects.
 *
 * An image holds a few dozen objects (at most FastOptions.max_objects, 256), so every pair's squared distance is
 * read directly (at most 65,536 of them) and the k smallest of a row kept by insertion: no tree to build, no
 * allocation but the caller's output.  Building scipy's cKDTree over them and querying it cost 0.14 ms an image
 * (its Python-side checks and arrays); this call costs a few microseconds.  Distances compare as scipy's do,
 * (dx dx) + (dy dy) in that order; equal distances rank the lower index first (scipy's order there was its
 * heap's); non-finite points are refused with ValueError, as scipy's tree refused them.
 */
#include "_kernel.h"

/* Row i: the k nearest of the n points (x, y interleaved in z) by squared distance, lower index first on ties. */
static void screen_knn_row(const double *z, Py_ssize_t n, Py_ssize_t i, Py_ssize_t k, double *best, int64_t *out)
{
    Py_ssize_t kept = 0;
    double xi = z[2 * i], yi = z[2 * i + 1];
    for (Py_ssize_t j = 0; j < n; j++) {  /* finite points: no NaN to order */
        double dx = z[2 * j] - xi, dy = z[2 * j + 1] - yi;
        double d2 = dx * dx + dy * dy;
        if (kept == k && !np_less(d2, best[k - 1])) {
            continue;  /* not closer than the k-th: a later j never displaces an equal earlier one */
        }
        Py_ssize_t at = kept < k ? kept++ : k - 1;
        while (at > 0 && np_less(d2, best[at - 1])) {
            best[at] = best[at - 1];
            out[at] = out[at - 1];
            at--;
        }
        best[at] = d2;
        out[at] = j;
    }
}

static PyObject *screen_knn(PyObject *self, PyObject *args)
{
    PyObject *oz, *oout;
    Arr a[2] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OO:screen_knn", &oz, &oout)) {
        return NULL;
    }
    if (arr_take(oz, &a[0], "z", 'Z', 1, 0, 0) || arr_take(oout, &a[1], "out", 'q', 2, 1, 0)) {
        arr_release(a, 2);
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), k = arr_dim(&a[1], 1);
    if (k < 1 || k > n) {
        PyErr_Format(PyExc_ValueError, "out must have between 1 and %zd columns, got %zd", n, k);
    } else if (!arr_check_shape(&a[1], "out", n, k)) {
        for (Py_ssize_t j = 0; j < 2 * n; j++) {
            if (!isfinite(D(a[0])[j])) {  /* as scipy's tree refused them: no order among NaNs to answer */
                PyErr_SetString(PyExc_ValueError, "z must be finite");
                break;
            }
        }
    }
    if (PyErr_Occurred()) {
        arr_release(a, 2);
        return NULL;
    }
    double *best = PyMem_Malloc(sizeof(double) * (size_t)k);
    if (best == NULL) {
        arr_release(a, 2);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        screen_knn_row(D(a[0]), n, i, k, best, Q(a[1]) + i * k);
    }
    PyMem_Free(best);
    arr_release(a, 2);
    Py_RETURN_NONE;
}

PyMethodDef screen_methods[] = {
    {"screen_knn", screen_knn, METH_VARARGS,
     "screen_knn(z, out): each of the n image objects' k nearest (out: (n, k) int64; ties: lower index first)."},
    {NULL, NULL, 0, NULL},
};
