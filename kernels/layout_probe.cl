/* Reports sizeof/offsetof of the structs in hlbvh.h as the device compiles
 * them, so tests/test_layout.py can hold hlbvh_cl/layout.py to the header. */
#include "hlbvh.h"

#define REPORT(i, value) out[i] = (int)(value)
/* OpenCL C has no offsetof: measure from a real (never dereferenced) pointer. */
#define offsetof(T, field) \
    ((int)((__global char *)&((__global T *)out)->field - (__global char *)out))

__kernel void struct_layout(__global int *out)
{
    if (get_global_id(0) != 0)
        return;
    REPORT(0, sizeof(Aabb));
    REPORT(1, offsetof(Aabb, hi));
    REPORT(2, sizeof(FlatNode));
    REPORT(3, offsetof(FlatNode, left_hi));
    REPORT(4, offsetof(FlatNode, right_lo));
    REPORT(5, offsetof(FlatNode, right_hi));
    REPORT(6, offsetof(FlatNode, left));
    REPORT(7, offsetof(FlatNode, right));
    REPORT(8, offsetof(FlatNode, left_count));
    REPORT(9, offsetof(FlatNode, right_count));
    REPORT(10, sizeof(Triangle));
    REPORT(11, offsetof(Triangle, v1));
    REPORT(12, offsetof(Triangle, v2));
    REPORT(13, sizeof(TriangleRef));
    REPORT(14, offsetof(TriangleRef, prim_id));
    REPORT(15, sizeof(Ray));
    REPORT(16, offsetof(Ray, tmin));
    REPORT(17, offsetof(Ray, direction));
    REPORT(18, offsetof(Ray, tmax));
    REPORT(19, sizeof(Hit));
    REPORT(20, offsetof(Hit, geom_id));
    REPORT(21, offsetof(Hit, prim_id));
    REPORT(22, offsetof(Hit, u));
    REPORT(23, offsetof(Hit, v));
    REPORT(24, offsetof(Hit, normal));
    REPORT(25, sizeof(PinholeCamera));
    REPORT(26, offsetof(PinholeCamera, forward));
    REPORT(27, offsetof(PinholeCamera, right));
    REPORT(28, offsetof(PinholeCamera, up));
    REPORT(29, sizeof(ShadeParams));
    REPORT(30, offsetof(ShadeParams, light_intensity));
    REPORT(31, offsetof(ShadeParams, ambient));
    REPORT(32, offsetof(ShadeParams, sky_up));
    REPORT(33, offsetof(ShadeParams, sky_horizon));
    REPORT(34, offsetof(ShadeParams, sky_zenith));
    REPORT(35, offsetof(ShadeParams, ray_offset));
    REPORT(36, offsetof(ShadeParams, depth_near));
    REPORT(37, offsetof(ShadeParams, depth_far));
    REPORT(38, offsetof(ShadeParams, ao_distance));
    REPORT(39, offsetof(ShadeParams, ao_weight));
    REPORT(40, sizeof(WideNode));
    REPORT(41, offsetof(WideNode, hi_x));
    REPORT(42, offsetof(WideNode, lo_y));
    REPORT(43, offsetof(WideNode, hi_y));
    REPORT(44, offsetof(WideNode, lo_z));
    REPORT(45, offsetof(WideNode, hi_z));
    REPORT(46, offsetof(WideNode, child));
    REPORT(47, offsetof(WideNode, count));
}
