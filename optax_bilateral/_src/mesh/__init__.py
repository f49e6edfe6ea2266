"""Triangle meshes: Large Steps and its bilateral variant."""
