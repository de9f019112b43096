/* Arrays through the buffer protocol: the kernel's argument checks (see _kernel.h). */
#include "_kernel.h"

#include <string.h>


void arr_release(Arr *a, int count)
{
    for (int i = 0; i < count; i++) {
        if (a[i].held) {
            PyBuffer_Release(&a[i].view);
            a[i].held = 0;
        }
    }
}

/* The format letter of a buffer, without a byte-order prefix of the native order. */
static const char *arr_bare_format(const char *f)
{
    if (f == NULL) {
        return "B";
    }
    if (f[0] == '@' || f[0] == '=' || f[0] == '<') {
        return f + 1;
    }
    return f;
}

static int arr_format_is(const Py_buffer *v, char kind)
{
    const char *f = arr_bare_format(v->format);
    switch (kind) {
    case 'd': return strcmp(f, "d") == 0 && v->itemsize == 8;
    case 'Z': return strcmp(f, "Zd") == 0 && v->itemsize == 16;
    case '?': return strcmp(f, "?") == 0 && v->itemsize == 1;
    case 'q': return (strcmp(f, "q") == 0 || strcmp(f, "l") == 0) && v->itemsize == 8;
    case 'Q': return (strcmp(f, "Q") == 0 || strcmp(f, "L") == 0) && v->itemsize == 8;
    case 'i': return strcmp(f, "i") == 0 && v->itemsize == 4;
    case 'I': return strcmp(f, "I") == 0 && v->itemsize == 4;
    case 'B': return strcmp(f, "B") == 0 && v->itemsize == 1;
    default: return 0;
    }
}

static const char *arr_kind_name(char kind)
{
    switch (kind) {
    case 'd': return "float64";
    case 'Z': return "complex128";
    case '?': return "bool";
    case 'Q': return "uint64";
    case 'i': return "int32";
    case 'I': return "uint32";
    case 'B': return "uint8";
    default: return "int64";
    }
}

/* Take a C-contiguous buffer of format ``kind`` and ``ndim`` dimensions from ``obj`` (None allowed when
 * ``optional``: then nothing is held).  Returns 0, or -1 with TypeError / ValueError set. */
int arr_take(PyObject *obj, Arr *a, const char *name, char kind, int ndim, int writable, int optional)
{
    a->held = 0;
    if (obj == Py_None && optional) {
        return 0;
    }
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (!PyObject_CheckBuffer(obj)) {
        PyErr_Format(PyExc_TypeError, "%s must be a %s array, got %.100s", name, arr_kind_name(kind),
                     Py_TYPE(obj)->tp_name);
        return -1;
    }
    if (PyObject_GetBuffer(obj, &a->view, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous%s array", name, writable ? " writable" : "");
        return -1;
    }
    a->held = 1;
    if (!arr_format_is(&a->view, kind)) {
        PyErr_Format(PyExc_TypeError, "%s must be %s, got buffer format '%s'", name, arr_kind_name(kind),
                     a->view.format ? a->view.format : "B");
        arr_release(a, 1);
        return -1;
    }
    if (a->view.ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s must be %d-D, got %d-D", name, ndim, a->view.ndim);
        arr_release(a, 1);
        return -1;
    }
    return 0;
}

Py_ssize_t arr_dim(const Arr *a, int axis)
{
    return a->held ? a->view.shape[axis] : -1;
}

int arr_check_shape(const Arr *a, const char *name, Py_ssize_t rows, Py_ssize_t cols)
{
    if (!a->held) {
        return 0;
    }
    if (arr_dim(a, 0) != rows || (a->view.ndim > 1 && arr_dim(a, 1) != cols)) {
        if (a->view.ndim > 1) {
            PyErr_Format(PyExc_ValueError, "%s must have shape (%zd, %zd), got (%zd, %zd)", name, rows, cols,
                         arr_dim(a, 0), arr_dim(a, 1));
        } else {
            PyErr_Format(PyExc_ValueError, "%s must have shape (%zd,), got (%zd,)", name, rows, arr_dim(a, 0));
        }
        return -1;
    }
    return 0;
}
