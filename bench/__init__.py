"""hlbvh_cl's benchmarks.

    python -m bench [--quick] [--devices pocl,intel]   the whole suite -> bench/RESULTS.md

The suite (bench/__main__.py) runs the pieces below, which also run alone:
    bench/build.py   build times per stage, tree quality, refit, sort peers
    bench/trace.py   ray throughput against Embree, Open3D, Mitsuba 3, trimesh
    bench/render.py  build + render timings of scene files (the report's table)
    bench/report.py  RESULTS.md and the plots, from the suite's JSON
"""
