"""Queries: visitors of the one walk of a built Tree (kernels/query/).

Closest and any hit (rays), every hit and counts (all_hits), nearest points
and winding numbers (points), the coherent orders they trace big batches in
(order), and the host memory of results (results).  It imports core,
device, parallel and build (the instanced tree's records)."""
