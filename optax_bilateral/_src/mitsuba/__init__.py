"""The Mitsuba 3 bridge: scene tensors to JAX and the drop-in Dr.Jit optimizers."""
