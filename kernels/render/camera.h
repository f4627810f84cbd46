/* The camera as the ray generation stage (render/camera.cl) reads it.
 * Mirrored by hlbvh_cl/core/layout.py. */
#ifndef CAMERA_H
#define CAMERA_H

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

#endif /* CAMERA_H */
