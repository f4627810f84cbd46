"""Scene I/O: TOML scene files and mesh files read as scenes (scenefile),
and the edge splitting they may ask for (split).  It imports core, the
public Scene and Mesh, and render (cameras, lights, renderers)."""
