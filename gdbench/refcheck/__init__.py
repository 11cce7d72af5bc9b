"""The renderer's reference checks: the backend registry, the comparison harness, golden
images, the reference scenes and the reference benchmarks."""
