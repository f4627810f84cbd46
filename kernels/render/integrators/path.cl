/* The path integrator's stages (hlbvh_cl/render/integrators/path.py, which
 * documents the estimator): unidirectional path tracing with next-event
 * estimation and BSDF sampling combined by the power heuristic (Veach 1997,
 * ch. 9; pbrt-v4's PathIntegrator, Mitsuba 3's path), and Russian roulette,
 * run as a wavefront (Laine, Karras & Aila 2013): one kernel per stage over
 * the pass's paths, whose states live in a device buffer.  Closest-hit and
 * shadow rays are traced between the stages by query/rays.cl.
 *
 * Kernels (one work-item per live path of the pass, in ray order; the
 * first pass's paths are the camera's rays, a later pass's those that went
 * on, compacted into its first live[depth] slots with their path numbers)
 *   path_surface    at the path's hit (or miss; on the first pass, a fresh
 *                   path): the light it sees there, a light sample (its
 *                   shadow ray, what it carries to `pending` and its path,
 *                   in the pass's next free shadow slot), and the next ray,
 *                   sampled from the BSDF, in the next pass's next free slot
 *   path_unoccluded a path's radiance += pending where its shadow ray was
 *                   free
 *   path_finish     the film's sum += each path's radiance (by path)
 *   path_aovs       (when asked, before the first path_surface) each pixel's
 *                   sums of its first hit's albedo, shading normal and depth
 *   path_aov_add    a band's AOV sums added to the whole image's
 *
 * Normals (Mitsuba 3's rules): BSDFs and area emitters see the shading
 * normal (shading_normal: interpolated vertex normals, or the geometric one
 * for face normals), so it decides which side a BSDF or an emitter shows;
 * the geometric normal decides only on which side a new ray starts (Mitsuba's
 * spawn_ray).  Nothing more corrects the shading normal, as in Mitsuba's path.
 *
 * Random numbers: random_unit(pixel, sample, dimension) (render/random.h),
 * the camera's dimensions 0 and 1, then 8 per bounce (light choice, 3 for
 * the light sample, 3 for the BSDF's, Russian roulette), whose salts
 * path_surface takes from the host (`salts`).
 */
#include "core/portable.h"
#include "core/launch.h"
#include "core/spelled.h"
#include "query/records.h"
#include "render/integrators/path.h"
#include "render/bsdfs/bsdf.h"
#include "render/surface.h"
#include "render/tiles.h"
#include "render/random.h"
#include "render/envmap.h"
#include "render/lights.h"

/* The power heuristic with beta = 2 (Veach 1997, eq. 9.13) for a sample
 * drawn with density `chosen` where the other strategy has `other`, as
 * 1 / (1 + (other / chosen)^2): the squares of a / (a + b) overflow for a
 * light that subtends a tiny solid angle (a lamp seen from 1e15 away, whose
 * density is past 1e30), where the weight was inf / inf, and underflow for
 * densities below 1e-19.  Both infinite: an even split. */
inline float power_heuristic(float chosen, float other)
{
    if (!(chosen > 0.0f))
        return 0.0f;
    float ratio = other / chosen;
    return ratio == ratio ? 1.0f / (1.0f + ratio * ratio) : 0.5f;
}

inline float luminance_max(float3 v)
{
    return v.x > v.y ? (v.x > v.z ? v.x : v.z) : (v.y > v.z ? v.y : v.z);
}

/* The tables a path vertex reads besides its own state (path_surface's
 * arguments of the same names), gathered so that the stages' helpers take
 * them as one: the lights' (render/lights.h), and the shading normals and
 * instances'. */
typedef struct {
    LightTables lights;
    __global const uint* shading_faces;      /* 3 vertices per triangle */
    __global const float* shading_normals;   /* 3 floats per vertex */
    __global const int* hit_instances;       /* per ray */
    __global const float* instance_maps;     /* 9 floats per instance */
    __global const int* instance_materials;  /* per instance: its material, -1: its mesh's */
} PathTables;

/* The shading normal at a hit, as Mitsuba 3's Mesh::compute_surface_interaction
 * takes it: the mesh's vertex normals interpolated by the hit's barycentrics
 * (u for v1, v for v2) and normalised, mapped to the world by the hit
 * instance's inverse transpose (9 floats, row-major, per instance); the unit
 * geometric normal for a mesh with face normals (shading_base < 0). */
inline float3 shading_normal(__global const Hit* hit, __global const PathMaterial* m,
                             int instance, __global const uint* shading_faces,
                             __global const float* shading_normals,
                             __global const float* instance_maps, uint instance_count)
{
    float3 geometric = LOAD_XYZ(hit->normal);
    if (m->shading_base < 0)
        return geometric;
    __global const uint* f = shading_faces + 3 * ((size_t)m->shading_base + (uint)hit->prim_id);
    float3 n0 = LOAD_XYZ(shading_normals + 3 * (size_t)f[0]);
    float3 n = n0 + hit->u * (LOAD_XYZ(shading_normals + 3 * (size_t)f[1]) - n0)
                  + hit->v * (LOAD_XYZ(shading_normals + 3 * (size_t)f[2]) - n0);
    if (instance >= 0 && (uint)instance < instance_count) {
        __global const float* a = instance_maps + 9 * (size_t)instance;
        n = (float3)(dot3(LOAD_XYZ(a), n), dot3(LOAD_XYZ(a + 3), n), dot3(LOAD_XYZ(a + 6), n));
    }
    float squared = dot3(n, n);
    return squared > 0.0f ? n * (1.0f / SQRT(squared)) : geometric;
}

/* The material a hit shows: its instance's own where the instance has one
 * (instance_materials, after the meshes' records), else its mesh's. */
inline __global const PathMaterial* hit_material(__global const Hit* hit, int instance,
                                                 __global const PathMaterial* materials,
                                                 __global const int* instance_materials,
                                                 uint instance_count)
{
    int own = instance >= 0 && (uint)instance < instance_count ? instance_materials[instance]
                                                               : -1;
    return materials + (own >= 0 ? own : hit->geom_id);
}

/* The radiance a path has gathered before this vertex: none on the first
 * pass (depth 0), which starts fresh paths. */
inline float3 radiance_before(__global const PathState* s, bool first)
{
    return first ? (float3)(0.0f) : LOAD_XYZ(s->radiance);
}

/* How far off the surface at x a new ray starts: Mitsuba 3's
 * Interaction::offset_p, (1 + max |x_i|) RayEpsilon, along the geometric
 * normal, with the 1 in the user's units, or the scene's largest coordinate
 * where that is smaller (params->ray_offset: integrators/path.py's
 * spawn_floor), so that neither a scene smaller than the user's unit loses
 * its shadows nor a large ground or backdrop lifts every ray of a small
 * object past its lights, as an offset from the scene's size did.  Mitsuba takes x from
 * the triangle's barycentrics; here x = o + t d, which is off by a few ulps
 * of |o| and of the distance t |d| as well (a bounce 5e3 long onto a unit
 * sphere): X_ULPS of those are added. */
#define X_ULPS (8.0f * 0x1p-24f)
inline float spawn_offset(const PathParams* params, float3 x, float3 o, float distance)
{
    float ax = abs_float(x.x), ay = abs_float(x.y), az = abs_float(x.z);
    float ox = abs_float(o.x), oy = abs_float(o.y), oz = abs_float(o.z);
    float largest = ax > ay ? (ax > az ? ax : az) : (ay > az ? ay : az);
    float origin = ox > oy ? (ox > oz ? ox : oz) : (oy > oz ? oy : oz);
    return params->ray_offset + RAY_EPSILON * largest + X_ULPS * (origin + distance);
}

/* The path ends here, with what it gathered at this vertex: it takes no
 * slot in the next pass. */
inline void end_path(__global PathState* s, bool first, float3 gathered)
{
    store3(s->radiance, radiance_before(s, first) + gathered);
}

/* A vertex's light sample as its shadow ray: from `origin` along the unit
 * `direction` up to `reach`, carrying `carried` to the path where it is
 * free. */
typedef struct {
    float3 origin;
    float3 direction;
    float reach;
    float3 carried;
} ShadowRay;

/* One path vertex (the pass's path `item`, path number `path`): the light it
 * sees there, its light sample (*shadow, where it returns with *casts
 * set), and whether the path goes on, from *next_origin along
 * *next_direction. */
FORCE_INLINE bool shade_vertex(uint item, uint path, int depth, uint first_pixel, uint8 salts,
                               __global const Ray* rays, __global const Hit* hits,
                               __global PathState* states, const PathTables* tables,
                               const PathParams* params, ShadowRay* shadow, bool* casts,
                               float3* next_origin, float3* next_direction)
{
    __global PathState* s = states + path;
    __global const Ray* ray = rays + item;
    float3 d = LOAD_XYZ(ray->direction);
    __global const Hit* hit = hits + item;
    float length_d = length3(d);
    float3 wo = -d / length_d;  /* unit, towards where the path came from */
    bool first = depth == 0;
    float3 throughput = first ? (float3)(1.0f) : LOAD_XYZ(s->throughput);
    float bsdf_pdf = first ? 0.0f : s->bsdf_pdf;
    float3 gathered = (float3)(0.0f);

    if (hit->geom_id < 0) {  /* the environment */
        float light_pdf;
        float3 escaped = environment_light(params, tables->lights.envmap_image,
                                           tables->lights.envmap_cdf, -wo, &light_pdf);
        float weight = bsdf_pdf > 0.0f ? power_heuristic(bsdf_pdf, light_pdf) : 1.0f;
        end_path(s, first, throughput * escaped * weight);
        return false;
    }
    int instance = tables->hit_instances[item];
    __global const PathMaterial* m = hit_material(hit, instance, tables->lights.materials,
                                                  tables->instance_materials,
                                                  params->instance_maps);
    float3 geometric = LOAD_XYZ(hit->normal);
    float3 shading = shading_normal(hit, m, instance, tables->shading_faces,
                                    tables->shading_normals, tables->instance_maps,
                                    params->instance_maps);
    float cos_out = dot3(shading, wo);
    float3 emitted = LOAD_XYZ(m->radiance);
    if (cos_out > 0.0f && luminance_max(emitted) > 0.0f) {
        float distance = hit->t * length_d;
        float weight = bsdf_pdf > 0.0f
            ? power_heuristic(bsdf_pdf, emitter_density(params, m, LOAD_XYZ(ray->origin),
                                                        distance, cos_out))
            : 1.0f;
        gathered += throughput * emitted * weight;
    }
    bool last = params->max_depth > 0 && depth + 1 >= params->max_depth;
    /* n: the BSDF's normal, turned to the viewer for one with sides */
    float3 n = shading;
    if (bsdf_has_sides(m) && !(cos_out > 0.0f)) {
        if (!m->twosided)
            last = true;  /* the back of a one-sided BSDF is black */
        n = -n;
    }
    if (last || cos_out == 0.0f) {
        end_path(s, first, gathered);
        return false;
    }
    float3 o = LOAD_XYZ(ray->origin), x = o + hit->t * d;
    /* secondary rays start off the surface on their own side of it */
    float offset = spawn_offset(params, x, o, hit->t * length_d);
    uint pixel = first_pixel + path;

    /* next-event estimation, for a BSDF with a density: one light sample,
     * weighed against the BSDF's density of its direction (delta lights: no MIS) */
    bool delta_light = false;
    LightSample light = {(float3)(0.0f), 0.0f, (float3)(0.0f), 0.0f};
    if (bsdf_has_density(m))
        light = sample_light(x, params, &tables->lights, pixel, salts.lo, &delta_light);
    float bsdf_pdf_of_light;
    float3 f_cos = light.pdf > 0.0f ? bsdf_eval(m, n, wo, light.direction, &bsdf_pdf_of_light)
                                    : (float3)(0.0f);
    if (light.pdf > 0.0f && luminance_max(f_cos * light.radiance) > 0.0f) {
        float weight = delta_light ? 1.0f : power_heuristic(light.pdf, bsdf_pdf_of_light);
        float3 carried = throughput * f_cos * light.radiance * (weight / light.pdf);
        /* The light was sampled from the surface point x, as Mitsuba's
         * sample_emitter_direction(si) takes it (its distance sets the
         * radiance and the density); the shadow ray leaves from x lifted on
         * the light's side (through a transmitting BSDF, or with shading
         * normals, the geometric back) towards the light's point, and
         * stops short of it by ShadowEpsilon of its length, which the
         * rounding of that point grows with: Mitsuba's spawn_ray_to.  A
         * light at infinity keeps its direction, and no end. */
        float3 toward = dot3(geometric, light.direction) > 0.0f ? geometric : -geometric;
        float3 direction = light.direction;
        float reach = INFINITY;
        if (light.reach < INFINITY) {
            float3 to_light = light.direction * light.reach - offset * toward;
            reach = length3(to_light);
            direction = to_light * (1.0f / reach);
            reach -= SHADOW_EPSILON * reach;
        }
        shadow->origin = x + offset * toward;
        shadow->direction = direction;
        shadow->reach = reach;
        shadow->carried = carried;
        *casts = true;
    }

    /* the BSDF sample: the throughput takes its weight f cos / pdf */
    BsdfSample next = bsdf_sample(m, n, wo, random_salted(pixel, salts.s4),
                                  random_salted(pixel, salts.s5), random_salted(pixel, salts.s6));
    throughput *= next.weight;
    float eta = (first ? 1.0f : s->eta) * next.eta;
    if (!(luminance_max(throughput) > 0.0f)) {
        end_path(s, first, gathered);
        return false;
    }
    /* Russian roulette (Mitsuba's rule): from rr_depth on, a path goes on
     * with probability q = min(max channel of its throughput * eta^2, 0.95) */
    if (depth + 1 >= params->rr_depth) {
        float q = luminance_max(throughput) * eta * eta;
        q = q < 0.95f ? q : 0.95f;
        if (!(random_salted(pixel, salts.s7) < q)) {
            end_path(s, first, gathered);  /* its light sample above still counts */
            return false;
        }
        throughput /= q;
    }
    store3(s->throughput, throughput);
    s->bsdf_pdf = next.delta ? 0.0f : next.pdf;  /* 0: the next emitter hit takes no MIS */
    s->eta = eta;
    store3(s->radiance, radiance_before(s, first) + gathered);
    float3 side = dot3(geometric, next.direction) > 0.0f ? geometric : -geometric;
    *next_origin = x + offset * side;
    *next_direction = next.direction;
    return true;
}

/* The leader's scan of its group's flags (path_surface): slots[i] holds
 * work-item i's goes_on | casts << 16 and becomes the paths and shadow rays
 * of the work-items before it, in the same halves; then the group reserves
 * its totals at *paths and *shadow_rays (the counts of the next pass's paths
 * and of this pass's shadow rays), giving the first of each (the shadow
 * rays' in *first_shadow).  A serial scan: a group is at most SURFACE_GROUP
 * (128) work-items, and neither a CPU nor a GPU pays for it the locked
 * instruction per work-item that local atomics cost a CPU runtime (one
 * that waits for the work-item's stores to drain). */
#if SURFACE_GROUP > 0xffff
#error "take_group_slots packs two counts of up to SURFACE_GROUP in 16 bits each"
#endif
#if SURFACE_GROUP_GPU > SURFACE_GROUP
#error "path_surface's local arrays hold SURFACE_GROUP work-items: a GPU's group must fit"
#endif
inline uint take_group_slots(__local uint* slots, __global uint* paths,
                             __global uint* shadow_rays, __local uint* first_shadow,
                             __local uint* totals)
{
    uint sum = 0, size = (uint)get_local_size(0);
    for (uint i = 0; i < size; ++i) {
        uint flags = slots[i];
        slots[i] = sum;
        sum += flags;
    }
    *totals = sum;
    uint taken = sum & 0xffffu, cast = sum >> 16;
    *first_shadow = cast > 0 ? atomic_add(shadow_rays, cast) : 0u;
    return taken > 0 ? atomic_add(paths, taken) : 0u;
}

/* Under PREFETCH (CPUs): how many work-items ahead path_surface asks for
 * the lines a later work-item of its group reads or writes at random (a
 * path's state) or into buffers far larger than the caches (the next
 * pass's rays, the shadow rays): a CPU runtime runs a group's work-items
 * one after another, and each such access stalled on its line (perf: the
 * stores of the next rays and shadow rays, on their write-allocate
 * misses).  Further ahead measured slower. */
#define STAGE_AHEAD 8u
#define STREAM_AHEAD 16u  /* 32 measured no faster */

/* NARROW_KERNEL (core/portable.h): Intel's CPU compiler packs a kernel's
 * work-items into its SIMD lanes unless a hint says otherwise; with this
 * one it runs them one by one (neither it nor PoCL vectorizes this kernel
 * across work-items: their build logs).  Packed 16 to an AVX-512 register
 * (no hint), this kernel came out wrong there besides: in a white furnace
 * 40 % of a mirror's reflected rays were lost, and on the Cornell box it
 * wrote rays that overflowed the walk's stack; with -cl-opt-disable, or
 * unpacked, it is right (on AVX2 hosts, 8 a register, the suite passed).
 * Packed 8 to a register on an AVX-512 host (intel_reqd_sub_group_size(8),
 * 2026.22) it is wrong too, in ways that change from run to run: in a
 * diffuse furnace only lane 0 of each 8 drew its own bounce, the others
 * another normal's, even from constant random numbers; lanes 6 and 7 lost
 * their paths until `tables` was made after the first barrier.  PoCL
 * ignores the hint: the same image there, bit for bit.
 *
 * The first pass (depth 0) starts fresh paths: throughput 1, no BSDF
 * density behind them, no radiance, eta 1 (these values, where later
 * passes read the path's state). */
NARROW_KERNEL
void path_surface(__global const Ray* rays,         /* the live paths' rays */
                           __global const Hit* hits,
                           __global const uint* paths,       /* their paths (depth > 0) */
                           __global PathState* states,       /* by path */
                           __global const PathMaterial* materials,  /* per geom_id */
                           __global const float* light_vertices,    /* 9 floats per triangle */
                           __global const float* light_normals,     /* 9 floats per triangle */
                           __global const float* light_cdf,
                           __global const int* light_geom,
                           __global const DeltaLight* delta_lights,
                           __global const uint* shading_faces,      /* 3 vertices per triangle */
                           __global const float* shading_normals,   /* 3 floats per vertex */
                           __global const int* hit_instances,       /* per ray */
                           __global const float* instance_maps,     /* 9 floats per instance */
                           __global const int* instance_materials,  /* per instance, -1: none */
                           __global const float* envmap_image,  /* H x W RGB (envmap.h) */
                           __global const float* envmap_cdf,    /* its marginal, conditionals */
                           const PathParams params,
                           const uint bound,          /* work-items: >= live[depth] */
                           const uint first_pixel,    /* the pass's first pixel: random streams */
                           const uint8 salts,         /* random_salt(sample, 2 + 8 depth + k) */
                           const int depth,           /* segments the paths have so far, - 1;
                                                       * 0: fresh paths */
                           __global uint* live,       /* live[depth]: paths in `rays`;
                                                       * live[depth + 1] += paths that go on */
                           __global Ray* next_rays,   /* the paths that go on, compacted */
                           __global uint* next_paths,
                           __global uint* shadows,    /* shadows[depth] += the shadow rays */
                           __global Ray* shadow,      /* the shadow rays, compacted */
                           __global float4* pending,  /* what each carries */
                           __global uint* shadow_paths)  /* and its path */
{
    /* compaction (Laine, Karras & Aila 2013, sec. 4): the paths that go on
     * take the next pass's first slots, and the shadow rays this pass's, so
     * that the walks' work-items past their counts (read on the device)
     * return at once instead of walking empty rays.  A work-group takes its
     * slots with one global atomic each for paths and shadow rays (an atomic
     * per path had the CPU threads contend for the counter's cache line),
     * and its work-items take theirs in local-id order from the leader's
     * serial scan of their flags (group_slots).  Slots follow no order across
     * groups: a path's numbers depend on its pixel, not its slot. */
    __local uint group_slots[SURFACE_GROUP];
    __local uint group_first, group_first_shadow, group_totals;
    uint lid = get_local_id(0);
    const PathTables tables = {{materials, light_vertices, light_normals, light_cdf,
                                light_geom, delta_lights, envmap_image, envmap_cdf},
                               shading_faces, shading_normals, hit_instances, instance_maps,
                               instance_materials};
    bool goes_on = false, casts = false;
    uint path = 0;
    float3 origin = (float3)(0.0f), direction = (float3)(0.0f);
    ShadowRay light = {(float3)(0.0f), (float3)(0.0f), 0.0f, (float3)(0.0f)};
    /* this pass's path count, read once per group: live[depth] shares its
     * cache line with live[depth + 1], which the groups on other cores add
     * to (take_group_slots), and a read per work-item missed on that line.
     * The launch is sized for the host's bound, which a later pass's count
     * may be a small part of: the groups that have paths are spread over it
     * (core/launch.h), and the others return at once, all of a group's
     * work-items together (past the barrier that gave them the count, before
     * the next).  The leader places the group, once: Intel's CPU compiler
     * left spread_group's 64-bit divisions in every work-item, which
     * measured slower there. */
    __local uint group_count, group_taken;
    uint size = (uint)get_local_size(0);
    if (lid == 0) {
        uint count = LESSER(live[depth], bound), taken;
        group_count = count;
        group_taken = spread_group(((ulong)count + size - 1u) / size, &taken) ? taken : UINT_MAX;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    uint count = group_count, taken = group_taken;
    if (taken == UINT_MAX)
        return;
    uint item = taken * size + lid;  /* this work-item's path of the pass */
    if (depth > 0 && item + STAGE_AHEAD < count)
        PREFETCH_AT(states + paths[item + STAGE_AHEAD], 1);
    /* and STREAM_AHEAD ahead the pass's rays and hits, which it reads in
     * order, and on the first pass the states it writes in order: a group
     * spans one 4 KB page of each, where the hardware's stream prefetch
     * stops, and it had missed on them (perf: the hit's and the ray's
     * first loads held a third of this kernel's samples on the first
     * pass, under a camera-only render) */
    if (item + STREAM_AHEAD < count) {
        PREFETCH_AT(rays + item + STREAM_AHEAD, 0);
        PREFETCH_AT(hits + item + STREAM_AHEAD, 0);
        if (depth == 0)
            PREFETCH_AT(states + item + STREAM_AHEAD, 1);
    }
    if (item < count) {
        path = depth == 0 ? item : paths[item];
        goes_on = shade_vertex(item, path, depth, first_pixel, salts, rays, hits, states,
                               &tables, &params, &light, &casts, &origin, &direction);
    }
    group_slots[lid] = (uint)goes_on | (uint)casts << 16;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0)
        group_first = take_group_slots(group_slots, live + depth + 1, shadows + depth,
                                       &group_first_shadow, &group_totals);
    barrier(CLK_LOCAL_MEM_FENCE);
    /* the group's slots are [first, first + its count): ask for the ones a
     * later work-item writes */
    if (lid + STAGE_AHEAD < (group_totals & 0xffffu))
        PREFETCH_AT(next_rays + group_first + lid + STAGE_AHEAD, 1);
    if (lid + STAGE_AHEAD < (group_totals >> 16)) {
        PREFETCH_AT(shadow + group_first_shadow + lid + STAGE_AHEAD, 1);
        PREFETCH_AT(pending + group_first_shadow + lid + STAGE_AHEAD, 1);
    }
    if (goes_on) {
        uint slot = group_first + (group_slots[lid] & 0xffffu);
        write_ray(next_rays + slot, origin, direction, INFINITY);
        next_paths[slot] = path;
    }
    if (casts) {
        uint shadow_slot = group_first_shadow + (group_slots[lid] >> 16);
        write_ray(shadow + shadow_slot, light.origin, light.direction, light.reach);
        pending[shadow_slot] = (float4)(light.carried, 0.0f);
        shadow_paths[shadow_slot] = path;
    }
}

/* After the shadow rays: a path's radiance += pending where its shadow ray
 * was free (a path casts one shadow ray a pass at most). */
NARROW_KERNEL
void path_unoccluded(__global const uchar* occluded,
                     __global const float4* pending,
                     __global const uint* shadow_paths,  /* as path_surface's */
                     __global const uint* shadows,
                     const int depth,
                     const uint bound,
                     __global PathState* states)
{
    uint gid = get_global_id(0);
    if (gid >= bound || gid >= shadows[depth] || occluded[gid])
        return;
    __global PathState* s = states + shadow_paths[gid];
    store3(s->radiance, LOAD_XYZ(s->radiance) + pending[gid].xyz);
}

NARROW_KERNEL
void path_finish(__global const PathState* states,
                 const uint count,
                 const uint sample,          /* 0 starts the sum */
                 __global float4* accum)
{
    uint gid = get_global_id(0);
    if (gid >= count)
        return;
    float4 before = sample == 0 ? (float4)(0.0f) : accum[gid];
    accum[gid] = before + (float4)(LOAD_XYZ(states[gid].radiance), 0.0f);
}

/* Mitsuba 3's aov integrator at the camera ray's hit: the albedo (here the
 * material's reflectance: diffuse reflectance, or a conductor's or
 * dielectric's specular reflectance), the world shading normal (sh_normal,
 * not turned to the viewer) and the depth (si.t: the distance along the
 * ray, `length_scale` back from the tree's frame); a miss gives zeros.
 * Each pixel sums them over its samples, two float4 per pixel: (albedo,
 * depth) and (normal, 0); sample 0 starts the sums. */
NARROW_KERNEL
void path_aovs(__global const Ray* rays,
               __global const Hit* hits,
               __global const PathMaterial* materials,
               __global const uint* shading_faces,
               __global const float* shading_normals,
               __global const int* hit_instances,
               __global const float* instance_maps,
               __global const int* instance_materials,
               const PathParams params,
               const float length_scale,
               const uint count,
               const uint sample,
               __global float4* aovs)
{
    uint gid = get_global_id(0);
    if (gid >= count)
        return;
    __global const Hit* hit = hits + gid;
    float4 first = (float4)(0.0f), second = (float4)(0.0f);
    if (hit->geom_id >= 0) {
        int instance = hit_instances[gid];
        __global const PathMaterial* m = hit_material(hit, instance, materials,
                                                      instance_materials, params.instance_maps);
        float reach = hit->t * length3(LOAD_XYZ(rays[gid].direction)) * length_scale;
        first = (float4)(LOAD_XYZ(m->reflectance), reach);
        second = (float4)(shading_normal(hit, m, instance, shading_faces,
                                         shading_normals, instance_maps, params.instance_maps),
                          0.0f);
    }
    if (sample != 0) {
        first += aovs[2 * (size_t)gid];
        second += aovs[2 * (size_t)gid + 1];
    }
    aovs[2 * (size_t)gid] = first;
    aovs[2 * (size_t)gid + 1] = second;
}

/* Over pixel_in_pass's 2D range (render/tiles.h): each pixel's AOV sums
 * added to the whole image's, 7 floats (albedo RGB, normal XYZ, depth); the
 * host divides by the samples each band took (the film's add_to_image). */
NARROW_KERNEL
void path_aov_add(__global const float4* aovs,
                  const uint width,
                  const uint first_row,
                  const uint rows,
                  __global float* image)
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    float4 first = aovs[2 * (size_t)gid], second = aovs[2 * (size_t)gid + 1];
    __global float* pixel = image + 7 * (size_t)((first_row + at.y) * width + at.x);
    pixel[0] += first.x;
    pixel[1] += first.y;
    pixel[2] += first.z;
    pixel[3] += second.x;
    pixel[4] += second.y;
    pixel[5] += second.z;
    pixel[6] += first.w;
}
