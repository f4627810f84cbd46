"""Scene I/O: TOML scene files and mesh files read as scenes (scenefile,
description), Mitsuba 3's XML read (mitsuba) and a TOML scene written as
XML (to_mitsuba), OpenEXR images (exr), and the edge splitting scene files
may ask for (split).  It imports core, the public Scene and Mesh, and
render (cameras, lights, renderers)."""
