"""Support that knows nothing of hands or tools: crash-safe files and folder locks (files.py), XLA's compilation
cache on disk (cache.py), the platform a kernel is traced for (platform.py), the evaluation's statistics
(stats.py), several processes of one run and one process's batch over its devices (distributed.py)."""
