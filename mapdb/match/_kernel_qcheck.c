/* The stored index's 4 KiB blocks checked in the kernel: a table-driven CRC-32 (the one zlib.crc32 computes:
 * reflected polynomial 0xEDB88320, initial and final XOR 0xFFFFFFFF), eight bytes a step ("slice-by-8").
 *
 * The lookup (_kernel_stored.c) checks the blocks of the quad ranges it reaches here (qcheck_quads), marking them in
 * the same flags array Python's Section uses, so it continues where it used to return the ranges for Python to
 * check.  A block's pages are asked of the OS first (MADV_WILLNEED), as Python's Section does.
 */
#include "_kernel_stored.h"

#include <stdlib.h>
#if defined(__unix__) || defined(__APPLE__)
#include <sys/mman.h>
#include <unistd.h>
#endif

#define QCHECK_GAP 8  /* lookup._PREFETCH_GAP */

static uint32_t qcheck_table[8][256];
static int qcheck_ready = 0;

/* The tables, made at the first use (under the GIL: no two threads make them at once). */
static void qcheck_init(void)
{
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int j = 0; j < 8; j++) {
            c = (c & 1) ? (c >> 1) ^ 0xEDB88320u : c >> 1;
        }
        qcheck_table[0][i] = c;
    }
    for (uint32_t i = 0; i < 256; i++) {
        for (int s = 1; s < 8; s++) {
            uint32_t prev = qcheck_table[s - 1][i];
            qcheck_table[s][i] = (prev >> 8) ^ qcheck_table[0][prev & 0xFF];
        }
    }
    qcheck_ready = 1;
}

uint32_t qcheck_crc32(uint32_t crc, const uint8_t *p, size_t n)
{
    if (!qcheck_ready) {
        qcheck_init();
    }
    uint32_t c = ~crc;
    while (n >= 8) {
        /* Bytes read one at a time: the result does not depend on the machine's byte order or alignment. */
        uint32_t lo = c ^ ((uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24);
        c = qcheck_table[7][lo & 0xFF] ^ qcheck_table[6][(lo >> 8) & 0xFF] ^ qcheck_table[5][(lo >> 16) & 0xFF]
            ^ qcheck_table[4][lo >> 24] ^ qcheck_table[3][p[4]] ^ qcheck_table[2][p[5]] ^ qcheck_table[1][p[6]]
            ^ qcheck_table[0][p[7]];
        p += 8;
        n -= 8;
    }
    while (n--) {
        c = (c >> 8) ^ qcheck_table[0][(c ^ *p++) & 0xFF];
    }
    return ~c;
}

static int qcheck_cmp(const void *a, const void *b)
{
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

/* Ask the OS for the blocks' pages at once (a cold lookup then waits for one round of reads in parallel, not one
 * page fault after another): runs of blocks closer than QCHECK_GAP in one call, as lookup.Section._prefetch. */
static void qcheck_prefetch(const uint8_t *raw, Py_ssize_t nbytes, const int64_t *blocks, Py_ssize_t n)
{
#if defined(MADV_WILLNEED) && defined(_SC_PAGESIZE)
    uintptr_t page = (uintptr_t)sysconf(_SC_PAGESIZE);
    for (Py_ssize_t i = 0, j; i < n && page > 0; i = j) {
        for (j = i + 1; j < n && blocks[j] - blocks[j - 1] <= QCHECK_GAP; j++) {
        }
        uintptr_t lo = (uintptr_t)(raw + (blocks[i] << STORED_BLOCK_BITS));
        int64_t end = (blocks[j - 1] + 1) << STORED_BLOCK_BITS;
        uintptr_t hi = (uintptr_t)(raw + (end < nbytes ? end : nbytes));
        lo -= lo % page;  /* madvise wants a page's start; a failure only means reading on demand */
        (void)madvise((void *)lo, (size_t)(hi - lo), MADV_WILLNEED);
    }
#else
    (void)raw, (void)nbytes, (void)blocks, (void)n;
#endif
}

int qcheck_quads(const StoredTables *t, StoredVec *blocks)
{
    Py_ssize_t n = 0, nbytes = t->n_quads * t->rb;
    if (blocks->n == 0) {
        return 0;
    }
    qsort(blocks->v, (size_t)blocks->n, sizeof(int64_t), qcheck_cmp);
    for (Py_ssize_t i = 0; i < blocks->n; i++) {
        if (n == 0 || blocks->v[i] != blocks->v[n - 1]) {
            blocks->v[n++] = blocks->v[i];
        }
    }
    blocks->n = n;
    if (n > 1) {
        qcheck_prefetch(t->quads, nbytes, blocks->v, n);
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        int64_t b = blocks->v[i], lo = b << STORED_BLOCK_BITS, hi = (b + 1) << STORED_BLOCK_BITS;
        hi = hi < nbytes ? hi : nbytes;
        if (t->q_mark[b]) {
            continue;
        }
        if (qcheck_crc32(0, t->quads + lo, (size_t)(hi > lo ? hi - lo : 0)) != t->q_crcs[b]) {
            return -(10 + STORED_BAD_BLOCK + (int)(b < INT32_MAX - 64 ? b : INT32_MAX - 64));
        }
        t->q_mark[b] = 1;
    }
    return 0;
}

static PyObject *py_qcheck_crc32(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer view;
    PyObject *start_obj = NULL;
    if (!PyArg_ParseTuple(args, "y*|O!:qcheck_crc32", &view, &PyLong_Type, &start_obj)) {
        return NULL;
    }
    unsigned long long start = start_obj ? PyLong_AsUnsignedLongLong(start_obj) : 0;
    if (start_obj && (PyErr_Occurred() || start > 0xFFFFFFFFull)) {
        PyErr_Clear();  /* an OverflowError (a negative start) is a ValueError here, as a start past 32 bits */
        PyBuffer_Release(&view);
        PyErr_SetString(PyExc_ValueError, "qcheck_crc32: start must be in [0, 2**32)");
        return NULL;
    }
    uint32_t c = qcheck_crc32((uint32_t)start, (const uint8_t *)view.buf, (size_t)view.len);
    PyBuffer_Release(&view);
    return PyLong_FromUnsignedLong(c);
}

PyMethodDef qcheck_methods[] = {
    {"qcheck_crc32", py_qcheck_crc32, METH_VARARGS,
     "qcheck_crc32(data, start=0): the CRC-32 of a bytes-like object, as zlib.crc32(data, start)."},
    {NULL, NULL, 0, NULL},
};
