"""The paper's experiments, reproduced: texture and volume recovery, meshes, mixed pytrees,
and the figures the README and the docs show (docs/experiments.md)."""
