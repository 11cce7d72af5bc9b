"""Stable Diffusion as a prior (``prior``), 3DFuse's conditioning (``threedfuse``) and the tiny
offline models the tests use (``tiny``)."""
