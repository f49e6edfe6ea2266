"""Triangle meshes: Large Steps and its bilateral variant. ``config`` (the settings),
``laplacian`` (the Laplacian and its solves), ``normals`` (normals, directions, the bilateral
normal filter), ``transforms`` (the optax transforms), ``alias`` (the optimizers) and
``deprecated`` (0.1.0's names)."""
