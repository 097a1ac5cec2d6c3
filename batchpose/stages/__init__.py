"""The job's stages, each ``main(...) -> Path`` writing one artifact; chained by :mod:`batchpose.run`."""
