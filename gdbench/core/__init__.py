"""The data types, conventions and plumbing every tier uses: cameras, scenes, PLY, files,
random draws, declared ranges, devices, progress, provenance, plots, the cache, turntables."""
