"""Benchmarks: ``bm_*.py`` modules, each a sweep of ``setup(**case) -> closure`` timed by
``common.timeit`` and written to CSV/JSON. Notebooks only read what these write."""
