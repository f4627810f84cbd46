"""Parallel primitives on the device: the LSD radix sort (radix_sort) and
the exclusive scan (scan) the build and the queries use.  It imports core
and device."""
