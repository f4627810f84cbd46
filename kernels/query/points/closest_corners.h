/* The point of the triangle (a, b, c) nearest to p, as barycentrics (u, v)
 * of b and c, and its squared distance to p (Ericson 2005, sec. 5.1.5: the
 * vertex, edge and face regions in turn), written once for the REAL type
 * that point.h includes it with (float, and double for slivers): the
 * functions are CORNERS(name).  Ericson's formulas divide by an edge's
 * squared length (edge regions) or by the squared area (face), so: an edge
 * region is taken only for an edge of nonzero length, and a point left in
 * the face region takes the nearest point of the three edges
 * (segment_point, exact for any triangle) when its face barycentrics are
 * out of range or NaN, and the nearer of that and the face point when
 * THIN(ab, ac) says the face formula may not be trusted. */

TRAVERSAL_INLINE REAL CORNERS(segment_point)(REAL3 a, REAL3 ab, REAL3 p, REAL* w)
{
    REAL length2 = DOT3(ab, ab);
    REAL along = length2 > 0.0f ? DOT3(p - a, ab) / length2 : 0.0f;
    along = GROW_LO(GROW_HI(along, 0.0f), 1.0f);
    *w = along;
    REAL3 d = p - (a + along * ab);
    return DOT3(d, d);
}

TRAVERSAL_INLINE REAL CORNERS(closest_on_corners)(REAL3 a, REAL3 b, REAL3 c, REAL3 p,
                                                   REAL* u_out, REAL* v_out)
{
    REAL3 ab = b - a, ac = c - a, ap = p - a;
    REAL u, v;
    REAL d1 = DOT3(ab, ap), d2 = DOT3(ac, ap);
    REAL3 bp = p - b;
    REAL d3 = DOT3(ab, bp), d4 = DOT3(ac, bp);
    REAL3 cp = p - c;
    REAL d5 = DOT3(ab, cp), d6 = DOT3(ac, cp);
    REAL vc = d1 * d4 - d3 * d2, vb = d5 * d2 - d1 * d6, va = d3 * d6 - d5 * d4;
    if (d1 <= 0.0f && d2 <= 0.0f) {                      /* vertex a */
        u = 0.0f;
        v = 0.0f;
    } else if (d3 >= 0.0f && d4 <= d3) {                 /* vertex b */
        u = 1.0f;
        v = 0.0f;
    } else if (vc <= 0.0f && d1 >= 0.0f && d3 <= 0.0f && d1 - d3 > 0.0f) { /* edge ab */
        u = d1 / (d1 - d3);
        v = 0.0f;
    } else if (d6 >= 0.0f && d5 <= d6) {                 /* vertex c */
        u = 0.0f;
        v = 1.0f;
    } else if (vb <= 0.0f && d2 >= 0.0f && d6 <= 0.0f && d2 - d6 > 0.0f) { /* edge ac */
        u = 0.0f;
        v = d2 / (d2 - d6);
    } else if (va <= 0.0f && d4 - d3 >= 0.0f && d5 - d6 >= 0.0f
               && (d4 - d3) + (d5 - d6) > 0.0f) {        /* edge bc */
        v = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        u = 1.0f - v;
    } else {                                             /* face */
        REAL inv = 1.0f / (va + vb + vc);
        u = vb * inv;
        v = vc * inv;
        bool inside = u >= 0.0f && v >= 0.0f && u + v <= 1.0f;
        if (!inside || THIN(ab, ac)) {
            REAL w, best = CORNERS(segment_point)(a, ab, p, &w);
            REAL eu = w, ev = 0.0f;
            REAL d = CORNERS(segment_point)(a, ac, p, &w);
            if (d < best) {
                best = d;
                eu = 0.0f;
                ev = w;
            }
            d = CORNERS(segment_point)(b, c - b, p, &w);
            if (d < best) {
                best = d;
                eu = 1.0f - w;
                ev = w;
            }
            REAL3 f = p - (a + u * ab + v * ac);
            if (!inside || best < DOT3(f, f)) {
                u = eu;
                v = ev;
            }
        }
    }
    *u_out = u;
    *v_out = v;
    REAL3 d = p - (a + u * ab + v * ac);
    return DOT3(d, d);
}
