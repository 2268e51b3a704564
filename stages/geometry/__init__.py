"""Layer ``geometry``: triangle meshes (reading, checking, PLY), built-in shapes, normalisation,
decimation, cameras, ray tracing and the ray-cache format. numpy only (no torch)."""
