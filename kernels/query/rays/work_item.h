/* What one work-item of a ray query reads and writes: which rays it traces
 * (PACKET_SIZE consecutive ones), loaded into RayLanes from Ray records or
 * from numpy-shaped arrays; the hits its walks leave, one lane each
 * (HitLanes); and a closest hit as a Hit record with its unit geometric
 * normal. */
#ifndef WORK_ITEM_H
#define WORK_ITEM_H

#include "query/records.h"
#include "query/normals.h"
#include "query/rays/ray.h"
#if PACKET_SIZE > 1
#include "query/rays/packet.h"
#endif

/* How many of the PACKET_SIZE rays from ray `at` exist below ray_count. */
TRAVERSAL_INLINE uint rays_from(uint ray_count, uint at)
{
    return at < ray_count ? LESSER((uint)PACKET_SIZE, ray_count - at) : 0u;
}

/* Work-item i traces rays [i * PACKET_SIZE, ...) : how many of them exist
 * (0 for the items past the end), and the first one. */
TRAVERSAL_INLINE uint packet_rays(uint ray_count, uint* first)
{
    *first = get_global_id(0) * PACKET_SIZE;
    return rays_from(ray_count, *first);
}

/* Under PREFETCH, asks for the cache lines of `bytes` bytes from `start`
 * (rw 1: to be written).  A prefetch may ask for memory past an array's
 * end, which it never reads: a prefetch never faults. */
#ifdef PREFETCH
#define PREFETCH_LINES(start, bytes, rw)                                              \
    for (uint line_ = 0; line_ < (uint)(bytes); line_ += 64)                           \
        PREFETCH_AT((__global const char*)(start) + line_, rw)
#else
#define PREFETCH_LINES(start, bytes, rw) do {} while (0)
#endif

/* The rays as Ray records (the renderer's); lanes past `used` repeat the
 * last ray. */
TRAVERSAL_INLINE void load_records(__global const Ray* rays, uint first, uint used,
                                   RayLanes* lanes)
{
    /* The next work-item's records, as load_arrays asks for its arrays
     * (perf: the loads of a path's bounce rays stalled on their lines). */
    PREFETCH_LINES(rays + (size_t)first + PACKET_SIZE, PACKET_SIZE * sizeof(Ray), 0);
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        __global const Ray* ray = rays + first + LESSER(l, used - 1);
        set_lane(lanes, l, LOAD_XYZ(ray->origin), LOAD_XYZ(ray->direction), ray->tmin,
                 ray->tmax);
    }
}

/* The rays of a later work-item, at slots[next, next + PACKET_SIZE) (those
 * below ray_count), and their results[slot] it will write, asked for
 * ahead: slots scatter them over the arrays, and each lane's load and store
 * would miss the cache (see load_arrays).  One ray at a time, spread over
 * the walk (a visitor's node hook calls prefetch_ahead): asked all at once,
 * their lines outnumber the misses a core keeps in flight and many
 * requests came to nothing (measured slower).  Without PREFETCH it does
 * nothing. */
typedef struct {
    __global const uint* slots;
    __global const float* origins;
    __global const float* directions;
    __global int* results;
    uint next, end;
} RaysAhead;

TRAVERSAL_INLINE void rays_ahead(RaysAhead* a, __global const uint* slots, uint next,
                                 uint ray_count, __global const float* origins,
                                 __global const float* directions, __global int* results)
{
    a->slots = slots;
    a->origins = origins;
    a->directions = directions;
    a->results = results;
    a->next = next;
    a->end = next < ray_count ? LESSER(next + PACKET_SIZE, ray_count) : next;
}

/* Asks for the next ray's lines, if one is left. */
TRAVERSAL_INLINE void prefetch_ahead(RaysAhead* a)
{
#ifdef PREFETCH
    if (a->next < a->end) {
        size_t slot = a->slots[a->next++];
        __builtin_prefetch(a->origins + 3 * slot);
        __builtin_prefetch(a->origins + 3 * slot + 2);
        __builtin_prefetch(a->directions + 3 * slot);
        __builtin_prefetch(a->directions + 3 * slot + 2);
        __builtin_prefetch(a->results + slot, 1);
    }
#endif
}

/* Asks for the rays the walk left (a short walk visits fewer nodes than a
 * work-item has rays). */
TRAVERSAL_INLINE void prefetch_rest(RaysAhead* a)
{
#ifdef PREFETCH
    while (a->next < a->end)
        prefetch_ahead(a);
#endif
}

/* Lane l's ray from slot at[l] of the arrays load_arrays reads. */
TRAVERSAL_INLINE void load_arrays_at(const uint* at, __global const float* origins,
                                     __global const float* directions,
                                     __global const float* tmin, uint tmin_step,
                                     __global const float* tmax, uint tmax_step,
                                     RayLanes* lanes)
{
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        uint i = at[l];
        set_lane(lanes, l, LOAD_XYZ(origins + 3 * (size_t)i), LOAD_XYZ(directions + 3 * (size_t)i),
                 tmin[i * tmin_step], tmax[i * tmax_step]);
    }
}

/* The rays as the arrays numpy users hand in (hlbvh_cl/query/rays.py): origins and
 * directions packed (x, y, z) per ray, tmin[i * tmin_step], tmax[i *
 * tmax_step] (step 0: every ray the same limit).  Results go to one array
 * per field, so that the host neither packs records nor picks fields out of
 * them (measured: that repacking took as long as tracing camera rays). */
TRAVERSAL_INLINE void load_arrays(uint first, uint used, __global const float* origins,
                                  __global const float* directions, __global const float* tmin,
                                  uint tmin_step, __global const float* tmax, uint tmax_step,
                                  RayLanes* lanes)
{
    /* The next work-item's rays (CPUs run a group's items in order): between
     * two work-items' loads lie thousands of random reads, and the hardware
     * prefetcher loses the stream (measured faster). */
    PREFETCH_LINES(origins + 3 * ((size_t)first + PACKET_SIZE), 3 * PACKET_SIZE * sizeof(float), 0);
    PREFETCH_LINES(directions + 3 * ((size_t)first + PACKET_SIZE),
                   3 * PACKET_SIZE * sizeof(float), 0);
    uint at[PACKET_SIZE];
    for (uint l = 0; l < PACKET_SIZE; ++l)
        at[l] = first + LESSER(l, used - 1);
    load_arrays_at(at, origins, directions, tmin, tmin_step, tmax, tmax_step, lanes);
}

/* The hits of a work-item's rays as their walks leave them (Found_ray,
 * Found_packet), one lane each: the triangle's tree-order index (-1: none),
 * its t, u, v, and on a two-level scene its instance. */
typedef struct {
    int index[PACKET_SIZE];
    float t[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE];
#ifdef INSTANCES
    int instance[PACKET_SIZE];
#endif
} HitLanes;

/* A walk's index (and instance) into lane l of out, or a packet's into
 * every lane: what an any-hit query reports. */
TRAVERSAL_INLINE void store_index_ray(const Found_ray* s, HitLanes* out, uint l)
{
    out->index[l] = s->index;
#ifdef INSTANCES
    out->instance[l] = s->instance;
#endif
}

/* ... and its t, u, v: what a closest-hit query reports. */
TRAVERSAL_INLINE void store_hit_ray(const Found_ray* s, HitLanes* out, uint l)
{
    store_index_ray(s, out, l);
    out->t[l] = s->t;
    out->u[l] = s->u;
    out->v[l] = s->v;
}

#if PACKET_SIZE > 1
TRAVERSAL_INLINE void store_index_packet(const Found_packet* s, HitLanes* out, uint l)
{
    vstore_packet(s->index, 0, out->index);
#ifdef INSTANCES
    vstore_packet(s->instance, 0, out->instance);
#endif
}

TRAVERSAL_INLINE void store_hit_packet(const Found_packet* s, HitLanes* out, uint l)
{
    store_index_packet(s, out, l);
    vstore_packet(s->t, 0, out->t);
    vstore_packet(s->u, 0, out->u);
    vstore_packet(s->v, 0, out->v);
}
#endif

#if PACKET_SIZE > 1
/* A packet's lanes as a vector and as floats (a union: see ChildEntries). */
typedef union {
    float_packet lanes;
    float lane[PACKET_SIZE];
} PacketFloats;

typedef union {
    int_packet lanes;
    int lane[PACKET_SIZE];
} PacketInts;

/* The unit geometric normals of the triangles a work-item's lanes hit
 * (found->index[l], lanes l < used; zero where none), all at once:
 * unit_vector's operations lane by lane, so the same bits as unit_normal
 * gives one by one, with one vector division, square root and division for
 * all the lanes where each lane took its own (measured faster on
 * incoherent rays: figures in the commit that says so).  The corners are
 * read once the walks are done, as the hits' ids are (closest_hits).
 * normal[k].lane[l]: lane l's component k. */
TRAVERSAL_INLINE void hit_normals(const HitLanes* found, uint used,
                                  __global const Leaf* triangles, PacketFloats normal[3])
{
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        float3 w = (float3)(0.0f);
        if (l < used && found->index[l] >= 0) {
            LEAF_CORNERS(tri, triangles, found->index[l]);
            w = triangle_cross(tri);
        }
        normal[0].lane[l] = w.x;
        normal[1].lane[l] = w.y;
        normal[2].lane[l] = w.z;
    }
    float_packet x = normal[0].lanes, y = normal[1].lanes, z = normal[2].lanes;
    float_packet largest = GROW_HI(GROW_HI(abs_packet(x), abs_packet(y)), abs_packet(z));
    float_packet scale = (float_packet)(1.0f) / largest;
    float_packet sx = x * scale, sy = y * scale, sz = z * scale;
    float_packet unit = (float_packet)(1.0f) / packet_root(sx * sx + sy * sy + sz * sz);
    int_packet zero = largest == (float_packet)(0.0f);  /* unit_vector keeps a zero vector */
    normal[0].lanes = zero ? x : sx * unit;
    normal[1].lanes = zero ? y : sy * unit;
    normal[2].lanes = zero ? z : sz * unit;
}
#endif

/* The unit geometric normal of triangle `index` (tree order; -1: none,
 * zero), one lane's. */
TRAVERSAL_INLINE float3 hit_normal(int index, __global const Leaf* triangles)
{
    if (index < 0)
        return (float3)(0.0f);
    LEAF_CORNERS(tri, triangles, index);
    return unit_normal(tri);
}

/* One ray's closest hit as a Hit record (a miss: t = INFINITY, ids -1, the
 * rest 0) from the tree-order index of the triangle hit (-1: none) and its
 * unit normal. */
TRAVERSAL_INLINE void make_hit(Hit* out, int index, float t, float u, float v, float3 normal,
                               __global const TriangleRef* refs)
{
    bool found = index >= 0;
    Hit hit;
    hit.t = found ? t : INFINITY;
    hit.geom_id = found ? refs[index].geom_id : -1;
    hit.prim_id = found ? refs[index].prim_id : -1;
    hit.u = found ? u : 0.0f;
    hit.v = found ? v : 0.0f;
    hit.normal[0] = normal.x;
    hit.normal[1] = normal.y;
    hit.normal[2] = normal.z;
    *out = hit;
}

#endif /* WORK_ITEM_H */
