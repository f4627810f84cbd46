"""hlbvh_cl's benchmarks, run from the repository root.

    python -m bench [--quick] [--devices pocl,intel] [--docs]   the suite -> RESULTS.md

The suite (bench/__main__.py) runs the pieces below; the first three also run alone:
    python -m bench.build    build times per stage, tree quality, refit
    python -m bench.trace    ray throughput against the peers (bench/peers.py)
    python -m bench.large    a 10M-triangle build and its memory
    bench/render.py          build + render timings of scene files
    bench/report.py          RESULTS.md; bench/plots.py its figures
The path tracer against Mitsuba 3, whole renders and then the renders' rays
depth by depth (where the gap lies):
    python -m bench.path        python -m bench.depth_rays
A change that claims speed measures it against the code before it, both
checkouts interleaved in one run, hits compared:
    python -m bench.ab BASE CHANGE [--devices pocl,intel]
Each writes its JSON and plot into bench/results/ (not committed); --docs
also writes the committed copies: bench/RESULTS.md and docs/bench_*.png.
"""
