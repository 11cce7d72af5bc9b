"""Procedural assets (meshes for the paper's prompts) and the image banks rendered from them."""
