/* What the path integrator's kernels (render/integrators/path.cl) read
 * besides the rays and hits; hlbvh_cl/render/integrators/path.py fills
 * them and documents the estimator.  Mirrored by hlbvh_cl/core/layout.py. */
#ifndef INTEGRATORS_PATH_H
#define INTEGRATORS_PATH_H

/* path_surface's work-groups (path.py's, read from here): SURFACE_GROUP
 * work-items on CPUs, its local arrays' length, and SURFACE_GROUP_GPU on
 * GPUs.  A group takes its slots in the next pass with one atomic add on a
 * counter every group shares (path.cl's take_group_slots), whose line the
 * CPU cores pass between them: 128 work-items a group measured faster than
 * 64 on both CPU runtimes.  A CPU runtime keeps the values a work-item
 * holds across the kernel's barriers in arrays of one element per
 * work-item, which must stay in L1: 256 was no faster on PoCL.  On a GPU
 * one work-item of the group scans the group's flags alone (serially),
 * while the others wait: there groups of 64 run well. */
#define SURFACE_GROUP 128
#define SURFACE_GROUP_GPU 64

/* Entries of a roughplastic's transmittance table (Mitsuba's resolution). */
#define TRANSMISSION_TABLE 64

/* A mesh's surface, by geom_id: its BSDF (render/bsdfs/) and its area
 * emission. */
typedef struct {
    float reflectance[3];    /* diffuse: the albedo; conductor, dielectric: specular_reflectance;
                              * plastic: diffuse_reflectance */
    uint twosided;           /* 1: both sides reflect; 0: the back side is black (Mitsuba's rule) */
    float radiance[3];       /* emitted on the front side, along the geometric normal (0: none) */
    float emitter_pdf;       /* the area density with which light sampling picks a point
                              * on this mesh: P(triangles) * lum(radiance) / sum(area * lum) */
    float eta[3];            /* conductor: the index's real part; dielectric, plastic:
                              * eta[0] = int_ior / ext_ior */
    uint bsdf;               /* BSDF_* (render/bsdfs/bsdf.h) */
    float k[3];              /* conductor: the index's imaginary part */
    float alpha;             /* rough BSDFs: the microfacet roughness */
    float transmittance[3];  /* dielectric: specular_transmittance */
    uint distribution;       /* rough BSDFs: MICROFACET_* (render/bsdfs/microfacet.h) */
    float specular[3];       /* plastic: specular_reflectance */
    float specular_weight;   /* plastic: the share of samples steered to the coating */
    float internal;          /* plastic: the coating's diffuse reflectance from inside */
    uint nonlinear;          /* plastic: 1 scales the internal reflection by the albedo */
    int shading_base;        /* the mesh's first triangle in the shading-normal tables;
                              * -1: face normals (Mitsuba's face_normals) */
    float reserved;
    float transmission[TRANSMISSION_TABLE];  /* roughplastic: the coating's transmittance
                                              * at cos theta = i / (TRANSMISSION_TABLE - 1) */
    float light_sphere[4];   /* an emitting analytic sphere's centre and radius (in the
                              * frame; render/lights.h's emitter_density); radius 0: none */
} PathMaterial;

/* A light of no extent, which light sampling alone can reach. */
typedef struct {
    float position[3];     /* point: where it is; directional: the unit direction light travels */
    uint type;             /* LIGHT_POINT or LIGHT_DIRECTIONAL */
    float value[3];        /* point: intensity (W/sr); directional: irradiance (W/m^2) */
    float probability;     /* the chance a light sample picks it */
} DeltaLight;

#define LIGHT_POINT 0
#define LIGHT_DIRECTIONAL 1

/* Mitsuba 3's RayEpsilon for float (1500 * 2^-24): a new ray starts
 * (1 + max |x_i|) RAY_EPSILON off the surface at x (path.cl's spawn_offset). */
#define RAY_EPSILON 0.0000894069671630859375f
/* And its ShadowEpsilon (10 RayEpsilon): a shadow ray stops this fraction of
 * its length short of the light (Mitsuba's spawn_ray_to). */
#define SHADOW_EPSILON 0.000894069671630859375f

typedef struct {
    float environment[3];           /* the constant environment's radiance */
    float environment_probability;  /* the chance a light sample goes to the environment
                                     * map (0 for a constant environment: BSDF sampling
                                     * alone reaches it, integrators/path.py) */
    float ray_offset;               /* RAY_EPSILON times 1 in the user's units, or the
                                     * largest coordinate where smaller (path.py's
                                     * spawn_floor), in the frame */
    uint light_triangles;           /* emissive triangles in light_cdf, its first entries */
    uint delta_lights;              /* DeltaLight records */
    int max_depth;                  /* Mitsuba's: the longest path, in segments; <= 0: no limit */
    int rr_depth;                   /* Russian roulette from this depth on */
    float delta_probability;        /* the chance a light sample picks a delta light */
    uint instance_maps;             /* normal maps per instance (0: a flat scene) */
    float envmap_to_world[9];       /* the environment map's rotation to the world, row-major */
    uint envmap_width;              /* its pixels per row; 0: the environment is constant */
    uint envmap_height;             /* its rows (render/envmap.h) */
    uint light_spheres;             /* emissive analytic spheres in light_cdf, after them */
} PathParams;

/* One path of the pass: what it still carries and what it has gathered;
 * 32 bytes, two to a cache line and none across two (path_unoccluded adds
 * to states at random). */
typedef struct {
    float throughput[3];
    float bsdf_pdf;   /* solid-angle density of the last bounce's direction; 0 after the camera */
    float radiance[3];
    float eta;        /* the product of the index ratios crossed (Russian roulette's eta^2) */
} PathState;

#endif /* INTEGRATORS_PATH_H */
