"""pyrender (OpenGL, offscreen with OSMesa) backends: Gaussian centres as points (camera and
depth conventions check) and textured meshes for the image banks. pyrender is imported
lazily; see ``_lib.import_pyrender``."""
