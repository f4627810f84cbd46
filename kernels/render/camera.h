/* The camera as the ray generation stage (render/camera.cl) reads it.
 * Mirrored by hlbvh_cl/core/layout.py. */
#ifndef CAMERA_H
#define CAMERA_H

#include "render/random.h"

/* A pinhole camera (hlbvh_cl/render/ fills it from a Camera, following
 * hlbvh_cl/io/scenefile.py's convention): the image-plane point (sx, sy) in
 * [-1, 1]^2, x to the right and y up, gets the ray
 * eye + t * (forward + sx * right + sy * up).  right and up are scaled by
 * tan(fov / 2), right also by the aspect ratio width / height. */
typedef struct {
    float eye[3];
    float forward[3];
    float right[3];
    float up[3];
} PinholeCamera;

/* Where sample `sample` of pixel `pixel` falls in the pixel's square, from
 * its top-left corner: the centre for jitter 0, uniform for jitter 1 (a box
 * filter's samples, and those a splatting filter spreads: film.cl).  The
 * camera and the film both call it, so they agree on every position. */
inline float2 pixel_offset(uint pixel, uint sample, int jitter)
{
    if (jitter != 1)
        return (float2)(0.5f);
    return (float2)(random_unit(pixel, sample, 0), random_unit(pixel, sample, 1));
}

#endif /* CAMERA_H */
