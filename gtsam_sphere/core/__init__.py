"""Layer 0, the numpy core: camera models, rays, geometry, minimal solvers, errors. No I/O."""
