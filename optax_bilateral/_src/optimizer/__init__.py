"""The optimizer: the per-leaf step, the leaf rule, the optax transforms, the alias, the
Laplacian pyramid and state I/O."""
