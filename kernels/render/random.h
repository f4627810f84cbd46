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

/* A number in [0, 1) fixed by (pixel, sample, dimension), the same on every
 * run and device.  24 bits, so that the float is exact. */
inline float random_unit(uint pixel, uint sample, uint dimension)
{
    uint h = hash_pcg(pixel + hash_pcg(sample + hash_pcg(dimension)));
    return (float)(h >> 8) * 0x1p-24f;
}

#endif /* RANDOM_H */
