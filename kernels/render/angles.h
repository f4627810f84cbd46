/* The sine and cosine of a fraction of a turn, the angle every sampling
 * routine draws (2 pi u): sincos itself reduces any angle, by Payne-Hanek
 * for large ones, and PoCL 3.0 calls it out of line; a fraction of a turn
 * reduces exactly instead.  Used by the path integrator's samplers; the
 * previews keep sincos (integrators/direct.cl). */
#ifndef RENDER_ANGLES_H
#define RENDER_ANGLES_H

/* sin(2 pi u), and cos(2 pi u) in *cosine, for u in [0, 2] (an
 * environment map one texel wide samples up to 1.5): u is
 * split into the nearest quarter turn k and a remainder f in [-1/2, 1/2]
 * (4u - k is exact, by Sterbenz's lemma), whose angle x = f pi / 2 lies in
 * [-pi/4, pi/4]; sin x and cos x are their Taylor polynomials there (to
 * x^9 and x^10, whose remainders are below 2e-9, under float's rounding),
 * and k turns them by quarter turns. */
inline float sincos_turn(float u, float* cosine)
{
    float quarters = 4.0f * u;
    int k = (int)(quarters + 0.5f);
    float x = (quarters - (float)k) * 1.5707963267948966f;
    float x2 = x * x;
    float s = x + x * x2 * (-1.0f / 6.0f + x2 * (1.0f / 120.0f + x2 * (-1.0f / 5040.0f
                                                                        + x2 * (1.0f / 362880.0f))));
    float c = 1.0f + x2 * (-0.5f + x2 * (1.0f / 24.0f + x2 * (-1.0f / 720.0f + x2 * (1.0f / 40320.0f
                                                                    + x2 * (-1.0f / 3628800.0f)))));
    /* quarter turn q: (sin, cos) = (s, c), (c, -s), (-s, -c), (-c, s), by
     * selects: Oclgrind ran a switch over q to wrong values */
    int q = k & 3;
    float sine = (q & 1) ? c : s, cos_out = (q & 1) ? s : c;
    *cosine = ((q + 1) & 2) ? -cos_out : cos_out;
    return (q & 2) ? -sine : sine;
}

#endif /* RENDER_ANGLES_H */
