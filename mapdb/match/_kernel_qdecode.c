/* The stored quad index's bit-packed blocks decoded (packed.py: coord_fields, neighbour_fields;
 * directory.py: Directory.decode's pages; binding.py: PageBoxes.check).
 *
 * A cold lookup (a place no lookup reached before) decodes the directory pages, coordinate blocks and neighbour
 * blocks it reaches; numpy's field reader (codec._read_fields) spent most of such a lookup building index arrays.
 * These loops read each field exactly as it does: the big-endian 64-bit window at the field's first byte, shifted
 * left by the bit offset, right by one, then right by 63 - width (a width of 0 gives 0).  Python keeps the checks
 * of the file (checksums, widths, lengths); every read here is bounds-checked again, so a wrong call raises
 * TypeError / ValueError and never reads outside the buffer.
 */
#include "_kernel_stored.h"

#include <string.h>

static PyObject *qdecode_bad(Arr *a, int count, const char *what)
{
    arr_release(a, count);
    PyErr_Format(PyExc_ValueError, "%s: a field lies outside the data or is wider than 57 bits", what);
    return NULL;
}

/* coord_fields(data, block_start, width, base, size) -> bytes of int64 (sum(size), 2): each block's first ``size``
 * objects' positions (its base plus the two fields at the block's widths). */
static PyObject *qdecode_coord_fields(PyObject *self, PyObject *args)
{
    PyObject *o[5];
    Arr a[5];
    if (!PyArg_ParseTuple(args, "OOOOO", &o[0], &o[1], &o[2], &o[3], &o[4])) {
        return NULL;
    }
    if (arr_take(o[0], &a[0], "data", 'B', 1, 0, 0) < 0) {
        return NULL;
    }
    const char *names[4] = {"block_start", "width", "base", "size"};
    const int dims[4] = {1, 2, 2, 1};
    for (int i = 1; i < 5; i++) {
        if (arr_take(o[i], &a[i], names[i - 1], 'q', dims[i - 1], 0, 0) < 0) {
            arr_release(a, i);
            return NULL;
        }
    }
    Py_ssize_t b = arr_dim(&a[1], 0), total = 0;
    if (arr_check_shape(&a[2], "width", b, 2) < 0 || arr_check_shape(&a[3], "base", b, 2) < 0
            || arr_check_shape(&a[4], "size", b, 0) < 0) {
        arr_release(a, 5);
        return NULL;
    }
    const int64_t *lo = Q(a[1]), *w = Q(a[2]), *base = Q(a[3]), *size = Q(a[4]);
    for (Py_ssize_t i = 0; i < b; i++) {
        if (size[i] < 0 || size[i] > STORED_NB_BLOCK || lo[i] < 0 || lo[i] > INT64_MAX / 16) {
            arr_release(a, 5);
            PyErr_SetString(PyExc_ValueError, "coord_fields: a block's size or first byte is out of range");
            return NULL;
        }
        total += size[i];
    }
    PyObject *out = PyBytes_FromStringAndSize(NULL, total * 16);
    if (out == NULL) {
        arr_release(a, 5);
        return NULL;
    }
    int64_t *xy = (int64_t *)PyBytes_AS_STRING(out);
    int bad = 0;
    for (Py_ssize_t i = 0; i < b && !bad; i++) {
        int64_t w0 = w[2 * i], w1 = w[2 * i + 1];
        if (w0 < 0 || w1 < 0 || w0 > PACKED_MAX_WIDTH || w1 > PACKED_MAX_WIDTH) {
            bad = 1;
            break;
        }
        for (int64_t j = 0; j < size[i]; j++) {
            int64_t at = lo[i] * 8 + j * (w0 + w1);
            *xy++ = base[2 * i] + (int64_t)packed_field(B(a[0]), a[0].view.len, at, w0, &bad);
            *xy++ = base[2 * i + 1] + (int64_t)packed_field(B(a[0]), a[0].view.len, at + w0, w1, &bad);
        }
    }
    if (bad) {
        Py_DECREF(out);
        return qdecode_bad(a, 5, "coord_fields");
    }
    arr_release(a, 5);
    return out;
}

/* One page: ``cells`` gaps (running sums from the page's first cell) and counts from bit ``at`` on (the two
 * widths already read). */
static void qdecode_page(const Arr *data, int64_t at, int64_t cells, int64_t wg, int64_t wc, int64_t *off,
                         int64_t *count, int *bad)
{
    int64_t run = 0;
    for (int64_t r = 0; r < cells; r++) {
        if (r > 0) {
            run += (int64_t)packed_field(B(*data), data->view.len, at + (r - 1) * wg, wg, bad);
        }
        off[r] = run;
        count[r] = (int64_t)packed_field(B(*data), data->view.len, at + (cells - 1) * wg + r * wc, wc, bad) + 1;
    }
}

/* Python's floor division and modulo (numpy's // and % of int64), for a divisor above 0. */
static inline int64_t qdecode_floordiv(int64_t a, int64_t b, int64_t *mod)
{
    int64_t q = a / b, r = a % b;
    if (r < 0) {
        r += b;
        q -= 1;
    }
    *mod = r;
    return q;
}

enum { QD_LO, QD_N, QD_DENSE, QD_SPAN, QD_SIDE, QD_LK, QD_QUAD0, QD_QUAD1, QD_CELL0, QD_COLS };

/* One directory page (row ``pg`` of the pages table) decoded into off / cnt (64 cells at most); 1 when it passes
 * directory.decode's checks (gaps above 0 after the first cell, cells within the combination's span, counts at most
 * max_cell, counts summing to the page's quads). */
static int qdecode_dir_page(const Arr *data, const int64_t *pg, int64_t max_cell, int64_t *off, int64_t *cnt,
                            int *bad)
{
    int64_t at = pg[QD_LO] * 8, n = pg[QD_N], sum = 0;
    int64_t wg = (int64_t)packed_field(B(*data), data->view.len, at, 8, bad);
    int64_t wc = (int64_t)packed_field(B(*data), data->view.len, at + 8, 8, bad);
    qdecode_page(data, at + 16, n, wg, wc, off, cnt, bad);
    int ok = !*bad;
    for (int64_t r = 0; r < n && ok; r++) {
        int64_t dense = (int64_t)((uint64_t)pg[QD_DENSE] + (uint64_t)off[r]);  /* numpy's int64 wraps */
        ok = (r == 0 || off[r] > off[r - 1]) && dense < pg[QD_SPAN] && cnt[r] <= max_cell;
        sum += cnt[r];
    }
    return ok && sum == pg[QD_QUAD1] - pg[QD_QUAD0];
}

/* Write a checked page's cells: key (its label combination, then its four cell coordinates), count, first quad. */
static void qdecode_dir_write(const int64_t *pg, const int64_t *off, const int64_t *cnt, int bits, uint64_t *key,
                              int64_t *count, int64_t *start)
{
    int64_t before = 0;
    for (int64_t r = 0; r < pg[QD_N]; r++) {
        int64_t c[4], d = (int64_t)((uint64_t)pg[QD_DENSE] + (uint64_t)off[r]);
        for (int j = 3; j > 0; j--) {
            d = qdecode_floordiv(d, pg[QD_SIDE], &c[j]);
        }
        c[0] = d;
        uint64_t k = (uint64_t)pg[QD_LK];
        for (int j = 0; j < 4; j++) {
            k = (k << bits) | (uint64_t)c[j];
        }
        Py_ssize_t at = (Py_ssize_t)(pg[QD_CELL0] + r);
        key[at] = k;
        count[at] = cnt[r];
        start[at] = pg[QD_QUAD0] + before;
        before += cnt[r];
    }
}

/* A pages table's rows in range: 1 to 64 cells, first byte and span at least 0, side above 0, cells inside the
 * directory's n_cells; else ValueError. */
static int qdecode_dir_rows(const int64_t *pages, Py_ssize_t p, Py_ssize_t n_cells)
{
    for (Py_ssize_t i = 0; i < p; i++) {
        const int64_t *pg = pages + i * QD_COLS;
        if (pg[QD_N] < 1 || pg[QD_N] > 64 || pg[QD_LO] < 0 || pg[QD_LO] > INT64_MAX / 16 || pg[QD_SIDE] < 1
                || pg[QD_CELL0] < 0 || pg[QD_CELL0] > (int64_t)n_cells - pg[QD_N]) {
            PyErr_SetString(PyExc_ValueError, "directory_pages: a page's row is out of range");
            return -1;
        }
    }
    return 0;
}

/* directory_pages(data, pages, bits, max_cell, key, count, start) -> bool: decode and check the pages (rows of
 * pages: QD_ columns); when every one passes, fill key, count, start at their cells and answer True; else write
 * nothing and answer False (the caller's MapFormatError). */
static PyObject *qdecode_directory_pages(PyObject *self, PyObject *args)
{
    PyObject *o[5];
    Arr a[5];
    int bits;
    long long max_cell;
    if (!PyArg_ParseTuple(args, "OOiLOOO", &o[0], &o[1], &bits, &max_cell, &o[2], &o[3], &o[4])) {
        return NULL;
    }
    if (bits < 1 || bits > 15) {
        PyErr_SetString(PyExc_ValueError, "directory_pages: bits must be in [1, 15]");
        return NULL;
    }
    if (arr_take(o[0], &a[0], "data", 'B', 1, 0, 0) < 0) {
        return NULL;
    }
    if (arr_take(o[1], &a[1], "pages", 'q', 2, 0, 0) < 0 || arr_take(o[2], &a[2], "key", 'Q', 1, 0, 0) < 0
            || arr_take(o[3], &a[3], "count", 'q', 1, 1, 0) < 0 || arr_take(o[4], &a[4], "start", 'q', 1, 1, 0) < 0) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t p = arr_dim(&a[1], 0), n_cells = arr_dim(&a[2], 0);
    if (a[2].view.readonly || arr_check_shape(&a[1], "pages", p, QD_COLS) < 0
            || arr_check_shape(&a[3], "count", n_cells, 0) < 0 || arr_check_shape(&a[4], "start", n_cells, 0) < 0
            || qdecode_dir_rows(Q(a[1]), p, n_cells) < 0) {
        if (!PyErr_Occurred()) {
            PyErr_SetString(PyExc_ValueError, "directory_pages: key must be writable");
        }
        arr_release(a, 5);
        return NULL;
    }
    int64_t off[64], cnt[64];
    int bad = 0, ok = 1;
    for (Py_ssize_t i = 0; i < p && ok; i++) {  /* every page checked before any is written */
        ok = qdecode_dir_page(&a[0], Q(a[1]) + i * QD_COLS, (int64_t)max_cell, off, cnt, &bad);
    }
    if (bad) {
        return qdecode_bad(a, 5, "directory_pages");
    }
    for (Py_ssize_t i = 0; i < p && ok; i++) {
        qdecode_dir_page(&a[0], Q(a[1]) + i * QD_COLS, (int64_t)max_cell, off, cnt, &bad);
        qdecode_dir_write(Q(a[1]) + i * QD_COLS, off, cnt, bits, (uint64_t *)a[2].view.buf, Q(a[3]), Q(a[4]));
    }
    arr_release(a, 5);
    return PyBool_FromLong(ok);
}

/* neighbour_fields(data, block_start, width, objects, k) -> bytes of int64 (m, k): each object's k neighbours
 * (its id plus the unzigzagged fields at its block's width), block_start and width given per object. */
static PyObject *qdecode_neighbour_fields(PyObject *self, PyObject *args)
{
    PyObject *o[4];
    Arr a[4];
    Py_ssize_t k;
    if (!PyArg_ParseTuple(args, "OOOOn", &o[0], &o[1], &o[2], &o[3], &k)) {
        return NULL;
    }
    if (arr_take(o[0], &a[0], "data", 'B', 1, 0, 0) < 0) {
        return NULL;
    }
    const char *names[3] = {"block_start", "width", "objects"};
    for (int i = 1; i < 4; i++) {
        if (arr_take(o[i], &a[i], names[i - 1], 'q', 1, 0, 0) < 0) {
            arr_release(a, i);
            return NULL;
        }
    }
    Py_ssize_t m = arr_dim(&a[3], 0);
    if (arr_check_shape(&a[1], "block_start", m, 0) < 0 || arr_check_shape(&a[2], "width", m, 0) < 0) {
        arr_release(a, 4);
        return NULL;
    }
    if (k < 0 || k > 1024) {
        arr_release(a, 4);
        PyErr_SetString(PyExc_ValueError, "neighbour_fields: k must be in [0, 1024]");
        return NULL;
    }
    const int64_t *lo = Q(a[1]), *w = Q(a[2]), *obj = Q(a[3]);
    PyObject *out = PyBytes_FromStringAndSize(NULL, m * k * 8);
    if (out == NULL) {
        arr_release(a, 4);
        return NULL;
    }
    int64_t *ids = (int64_t *)PyBytes_AS_STRING(out);
    int bad = 0;
    for (Py_ssize_t i = 0; i < m && !bad; i++) {
        if (obj[i] < 0 || obj[i] > INT64_MAX / 2 || lo[i] < 0 || lo[i] > INT64_MAX / 16 || w[i] < 0
                || w[i] > PACKED_MAX_WIDTH) {
            bad = 1;
            break;
        }
        for (Py_ssize_t j = 0; j < k; j++) {
            int64_t at = lo[i] * 8 + ((obj[i] % STORED_NB_BLOCK) * k + j) * w[i];
            *ids++ = obj[i] + packed_unzigzag(packed_field(B(a[0]), a[0].view.len, at, w[i], &bad));
        }
    }
    if (bad) {
        Py_DECREF(out);
        return qdecode_bad(a, 4, "neighbour_fields");
    }
    arr_release(a, 4);
    return out;
}

/* The page holding object ``id``: the last page whose first object is at most ``id`` (numpy's
 * searchsorted(start, id, side="right") - 1). */
static Py_ssize_t qdecode_page_of(const int64_t *start, Py_ssize_t n, int64_t id, Py_ssize_t *hint)
{
    Py_ssize_t h = *hint;
    /* A block's objects come in order: most are in the previous object's page or the next one. */
    for (Py_ssize_t p = h; p >= 0 && p < n - 1 && p <= h + 2 && start[p] <= id; p++) {
        if (id < start[p + 1]) {
            *hint = p;
            return p;
        }
    }
    Py_ssize_t lo = 0, hi = n;
    while (lo < hi) {
        Py_ssize_t mid = lo + (hi - lo) / 2;
        if (start[mid] <= id) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    *hint = lo - 1 >= 0 ? lo - 1 : 0;
    return lo - 1;
}

/* page_boxes(ids, xy, start, lo, hi, checked) -> int: -1 when every object ``ids`` at ``xy`` (m, 2) lies inside
 * its page's box (lo, hi: (P, 2), borders inside; start: each page's first object and the end), then those pages
 * marked in ``checked``; else the page of the first object outside (nothing marked: binding.PageBoxes.check). */
static PyObject *qdecode_page_boxes(PyObject *self, PyObject *args)
{
    PyObject *o[6];
    Arr a[6];
    if (!PyArg_ParseTuple(args, "OOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5])) {
        return NULL;
    }
    const char *names[5] = {"ids", "xy", "start", "lo", "hi"};
    const int dims[5] = {1, 2, 1, 2, 2};
    for (int i = 0; i < 5; i++) {
        if (arr_take(o[i], &a[i], names[i], 'q', dims[i], 0, 0) < 0) {
            arr_release(a, i);
            return NULL;
        }
    }
    if (arr_take(o[5], &a[5], "checked", '?', 1, 1, 0) < 0) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t m = arr_dim(&a[0], 0), pages = arr_dim(&a[3], 0);
    if (arr_check_shape(&a[1], "xy", m, 2) < 0 || arr_check_shape(&a[2], "start", pages + 1, 0) < 0
            || arr_check_shape(&a[4], "hi", pages, 2) < 0 || arr_check_shape(&a[5], "checked", pages, 0) < 0) {
        arr_release(a, 6);
        return NULL;
    }
    const int64_t *ids = Q(a[0]), *xy = Q(a[1]), *start = Q(a[2]), *lo = Q(a[3]), *hi = Q(a[4]);
    Py_ssize_t outside = -1, hint = 0;
    for (Py_ssize_t i = 0; i < m && outside < 0; i++) {
        Py_ssize_t p = qdecode_page_of(start, pages + 1, ids[i], &hint);
        if (p < 0 || p >= pages) {
            arr_release(a, 6);
            PyErr_SetString(PyExc_ValueError, "page_boxes: an object id is outside the pages");
            return NULL;
        }
        if (xy[2 * i] < lo[2 * p] || xy[2 * i + 1] < lo[2 * p + 1] || xy[2 * i] > hi[2 * p]
                || xy[2 * i + 1] > hi[2 * p + 1]) {
            outside = p;
        }
    }
    for (Py_ssize_t i = 0; i < m && outside < 0; i++) {
        B(a[5])[qdecode_page_of(start, pages + 1, ids[i], &hint)] = 1;
    }
    arr_release(a, 6);
    return PyLong_FromSsize_t(outside);
}

PyMethodDef qdecode_methods[] = {
    {"qdecode_page_boxes", qdecode_page_boxes, METH_VARARGS,
     "-1 when every object lies inside its map page's box (pages marked checked), else the first outside's page."},
    {"qdecode_coord_fields", qdecode_coord_fields, METH_VARARGS,
     "Positions (bytes of int64, (m, 2)) of packed coordinate blocks (packed.coord_fields)."},
    {"qdecode_directory_pages", qdecode_directory_pages, METH_VARARGS,
     "Decode and check directory pages into the directory's key, count and start arrays (Directory.decode)."},
    {"qdecode_neighbour_fields", qdecode_neighbour_fields, METH_VARARGS,
     "Neighbour ids (bytes of int64, (m, k)) of objects from packed blocks (packed.neighbour_fields)."},
    {NULL, NULL, 0, NULL},
};
