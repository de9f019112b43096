/* The stored index's 4 KiB blocks checked in the kernel: a table-driven CRC-32 (the one zlib.crc32 computes:
 * reflected polynomial 0xEDB88320, initial and final XOR 0xFFFFFFFF), eight bytes a step ("slice-by-8").
 *
 * The lookup (_kernel_stored.c) checks the blocks of the quad ranges it reaches here, marking them in the same flags
 * array Python's Section uses, so it continues where it used to return the ranges for Python to check.
 */
#include "_kernel_stored.h"

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

int64_t qcheck_blocks(const uint8_t *raw, Py_ssize_t nbytes, const uint32_t *crcs, uint8_t *checked, int64_t first,
                      int64_t last)
{
    for (int64_t b = first; b <= last; b++) {
        if (checked[b]) {
            continue;
        }
        int64_t lo = b << STORED_BLOCK_BITS, hi = (b + 1) << STORED_BLOCK_BITS;
        hi = hi < nbytes ? hi : nbytes;
        if (qcheck_crc32(0, raw + lo, (size_t)(hi > lo ? hi - lo : 0)) != crcs[b]) {
            return b;
        }
        checked[b] = 1;
    }
    return -1;
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
