/* Deterministic random numbers for rendering: the PCG hash of Jarzynski &
 * Olano 2020 ("Hash Functions for GPU Rendering", JCGT 9(3)), an integer
 * hash good enough to be used without state. */
#ifndef RANDOM_H
#define RANDOM_H

inline uint hash_pcg(uint value)
{
    uint state = value * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

/* The part of random_unit's hash that every pixel of a sample shares: a
 * wavefront stage reads its dimensions' salts from the host (the path
 * integrator's, hlbvh_cl/render/random.py) rather than hash them again in
 * each work-item. */
inline uint random_salt(uint sample, uint dimension)
{
    return hash_pcg(sample + hash_pcg(dimension));
}

/* random_unit from its salt. */
inline float random_salted(uint pixel, uint salt)
{
    return (float)(hash_pcg(pixel + salt) >> 8) * 0x1p-24f;
}

/* A number in [0, 1) fixed by (pixel, sample, dimension), the same on every
 * run and device.  24 bits, so that the float is exact. */
inline float random_unit(uint pixel, uint sample, uint dimension)
{
    return random_salted(pixel, random_salt(sample, dimension));
}

#endif /* RANDOM_H */
