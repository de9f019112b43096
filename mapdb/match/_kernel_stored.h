/* The stored quad index's lookup in the kernel (_kernel_stored.c: cells, directory, bounds, best k;
 * _kernel_stored_resolve.c: records, neighbours, coordinates, canonical quads, filing checks).
 *
 * Python (mapdb.match.index.stored) keeps the file's integrity: it decodes and checks directory pages and checksums
 * blocks (but the quads section's, which the lookup checksums where it reaches them: _kernel_qcheck.c); the kernel reads only what Python has checked (the flags arrays it is given) and, where a lookup reaches
 * a page or block not checked yet, answers with what it needs (StoredNeeds) instead of hits: Python checks those
 * and asks again.  Every index and range read is bounds-checked, so a wrong table never crashes.
 */
#ifndef MAPDB_KERNEL_STORED_H
#define MAPDB_KERNEL_STORED_H

#include "_kernel.h"

#include <string.h>

#define STORED_TABLES 16
#define STORED_NB_BLOCK 64  /* packed.NB_BLOCK */
#define STORED_BLOCK_BITS 12  /* layout.BLOCK_BITS: 4 KiB checksum blocks */

/* The index's packed fields, read as the map's codec reads them (_kernel_qdecode.c, _kernel_stored_resolve.c). */
#define PACKED_MAX_WIDTH 57  /* codec._read_fields: fields of at most 57 bits */

/* The field of ``w`` bits at bit ``at`` of ``buf`` (``n`` bytes); 1 in *bad when its window leaves the buffer
 * or it is wider than PACKED_MAX_WIDTH. */
static inline uint64_t packed_field(const uint8_t *buf, Py_ssize_t n, int64_t at, int64_t w, int *bad)
{
    if (at < 0 || w < 0 || w > PACKED_MAX_WIDTH || (at >> 3) > (int64_t)n - 8) {
        *bad = 1;
        return 0;
    }
    uint64_t word;
    memcpy(&word, buf + (at >> 3), 8);
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    word = __builtin_bswap64(word);  /* the window is big-endian */
#endif
    uint64_t head = (word << (at & 7)) >> 1;
    return head >> (63 - w);
}

/* codec._unzigzag of a field (below 2^57, so its int64 is exact). */
static inline int64_t packed_unzigzag(uint64_t z)
{
    int64_t v = (int64_t)z;
    return (v % 2 == 0) ? v / 2 : -(v + 1) / 2;
}

/* Corruption found (the Python side raises MapFormatError with the matching message). */
enum { STORED_OK = 0, STORED_BAD_ID = 1, STORED_NOT_FILED = 2, STORED_BAD_RANGE = 3 };
/* A quads block whose checksum fails: its code is this plus the block's number. */
#define STORED_BAD_BLOCK 16

/* The index's arrays (StoredQuadIndex's sections, directory, neighbours, coordinates) as the kernel reads them. */
typedef struct {
    Arr a[STORED_TABLES];
    const uint8_t *quads, *q_checked, *decoded, *nb_width, *nb_data, *nb_checked, *co_decoded;
    const uint64_t *fence_key, *dir_key, *nb_start;
    const int64_t *first_cell, *dir_start, *dir_count, *triples;
    const int32_t *xy;
    const uint32_t *q_crcs;  /* the quads section's block checksums */
    uint8_t *q_mark;  /* q_checked, written as blocks pass (_kernel_qcheck.c) */
    Py_ssize_t n_quads, rb, q_blocks, n_pages, n_cells, n_triples, nb_blocks, nb_bytes, co_blocks;
    int sub_bits, triple_bits, bits, k_nb;
    int64_t n_objects, ox, oy;
    double quantum;
} StoredTables;

/* A lookup's query rows: invariants (m, 4), radii already clamped to their cells, cell sides, label keys; k hits a
 * row at most, about ``limit`` candidates handled at once. */
typedef struct {
    const double *q, *r, *cell;
    const int64_t *lk;
    Py_ssize_t m, k, limit;
} StoredAsk;

/* A growable int64 list. */
typedef struct {
    int64_t *v;
    Py_ssize_t n, cap;
} StoredVec;

/* What a lookup needs checked before it can answer: directory pages, quad ranges (start, count; none since the
 * kernel checks the quads blocks itself, the slot kept for the answer's shape), the objects whose neighbour blocks
 * and coordinate blocks are not checked yet. */
typedef struct {
    StoredVec pages, ranges, nb, co;
    StoredVec quads;  /* the quads blocks reached and not checked yet: the kernel checks them (qcheck_quads) */
} StoredNeeds;

int stored_push(StoredVec *s, int64_t x);
void stored_needs_free(StoredNeeds *nd);
int stored_needs_any(const StoredNeeds *nd);
/* A Python bytes object of the list's int64s. */
PyObject *stored_vec_bytes(const StoredVec *s);
/* A quad record's anchor, triple number and four positions inside its cell (packed.unpack_records). */
void stored_record(const StoredTables *t, Py_ssize_t at, int64_t *anchor, int64_t *triple, uint8_t *sub);
/* Resolve a quad: ids in canonical order and invariants.  0 when done, 1 when it needs blocks (recorded in
 * ``nd``), -1 on memory error, or -(10 + a STORED_ code) on corruption. */
int stored_resolve_one(const StoredTables *t, int64_t anchor, int64_t triple, StoredNeeds *nd, int64_t *ids,
                       double *inv);
/* 1 when invariants ``inv`` fall in the cell of ``key`` at positions ``sub`` (binding.check_filed's row). */
int stored_filed(const StoredTables *t, const double *inv, uint64_t key, const uint8_t *sub, double cell);
/* The tables from Python's tuple; 0, or -1 with TypeError / ValueError set (release with arr_release). */
int stored_take_tables(PyObject *tables, StoredTables *t);

/* The lookup of ``ask`` (_kernel_stored.c): (0, rows, ids, distances) as bytes, the rows renamed by ``row_of`` when
 * not NULL; (1, needs ...) or (2, code) as stored_lookup answers; NULL with an error set. */
PyObject *stored_run(const StoredTables *t, const StoredAsk *ask, const int64_t *row_of);

/* _kernel_qcheck.c: zlib's CRC-32 of ``n`` bytes continued from ``crc``; the blocks ``first..last`` of ``raw``
 * (``nbytes`` long, 4 KiB blocks) not yet ``checked`` checked against ``crcs`` and marked: -1, or the first that fails. */
uint32_t qcheck_crc32(uint32_t crc, const uint8_t *p, size_t n);
/* The quads blocks in ``blocks`` (sorted and made unique in place) asked of the OS at once, then checked and marked
 * in ascending order: 0, or -(10 + STORED_BAD_BLOCK + the first that fails). */
int qcheck_quads(const StoredTables *t, StoredVec *blocks);

#endif
