/* Reports what the device's compiler targets, from its own predefined
 * macros (hlbvh_cl/device/profile.py, vector_width): a runtime's reported vector
 * width can differ from the instructions its compiler emits. */
__kernel void compile_target(__global int *out)
{
    if (get_global_id(0) != 0)
        return;
    int flags = 0;
#if defined(__x86_64__) || defined(__i386__)
    flags |= 1;
#endif
#ifdef __AVX__
    flags |= 2;
#endif
#ifdef __AVX512F__
    flags |= 4;
#endif
    out[0] = flags;
}
