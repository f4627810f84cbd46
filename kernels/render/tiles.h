/* The order in which rendering traces a pass's pixels.  A pass is whole
 * image rows, cut into bands of TILE_ROWS rows, and bands into tiles of
 * TILE_COLUMNS x TILE_ROWS pixels, left to right, each tile row-major; a
 * band's last width % TILE_COLUMNS columns, and a last band of fewer rows,
 * stay row-major.  A CPU ray packet (query/rays.cl: 16 or 8 rays, the kernel
 * variant's packet size) then covers a tile or half of one rather than a
 * strip of a row, which measured faster than row-major order for
 * closest-hit and shadow rays, and 4x4 tiles with packets of 16 faster than
 * 4x2 with packets of 8.  hlbvh_cl/core/layout.py reads TILE_ROWS and
 * TILE_COLUMNS from this file.
 *
 * The kernels that map rays to pixels run over a 2D range
 * (TILE_ROWS * width, bands): work-item (k, band) is the pass's ray
 * band * TILE_ROWS * width + k, and its pixel takes no integer division
 * (CPU devices run those one lane at a time, measured slow on PoCL). */
#ifndef TILES_H
#define TILES_H

#include "core/spelled.h"

#define TILE_COLUMNS 4
#define TILE_ROWS 4

/* How many of the multiples value, 2 value, ... (TILE_ROWS - 1) value are
 * <= k: k / value when that is below TILE_ROWS, without a division. */
inline uint rows_below(uint k, uint value)
{
    uint y = 0;
    for (uint r = 1; r < TILE_ROWS; ++r)
        y += k >= r * value;
    return y;
}

/* The ray and the pixel (column, row within the pass) of work-item
 * (k, band) of a pass of `rows` rows; false if it has none. */
inline bool pixel_in_pass(uint k, uint band, uint width, uint rows, uint *ray, uint2 *pixel)
{
    uint first_row = band * TILE_ROWS;
    if (first_row >= rows)
        return false;
    uint band_rows = LESSER((uint)TILE_ROWS, rows - first_row);
    if (k >= band_rows * width)
        return false;
    uint tiled = (width & ~(TILE_COLUMNS - 1u)) * TILE_ROWS;
    uint x, y;
    if (band_rows < TILE_ROWS) { /* the pass's last band, of fewer rows */
        y = rows_below(k, width);
        x = k - y * width;
    } else if (k < tiled) {
        x = k / (TILE_COLUMNS * TILE_ROWS) * TILE_COLUMNS + k % TILE_COLUMNS;
        y = k / TILE_COLUMNS % TILE_ROWS;
    } else { /* the last width % TILE_COLUMNS columns */
        uint columns = width % TILE_COLUMNS, rest = k - tiled;
        y = rows_below(rest, columns);
        x = width - columns + rest - y * columns;
    }
    *ray = first_row * width + k;
    *pixel = (uint2)(x, first_row + y);
    return true;
}

#endif /* TILES_H */
