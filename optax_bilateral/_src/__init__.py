"""Private implementation modules; the public names are re-exported by optax_bilateral."""
