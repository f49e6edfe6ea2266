"""Toy differentiable renderers with genuine Monte Carlo gradient noise (JAX, CPU-friendly).

Each module models only what one of the paper's experiments needs:

* ``optax_bilateral.toy.texture``: a glossy plane with a GGX roughness texture lit
  by an environment (main paper Fig. 5; ``experiments/paper/texture.py``).
* ``optax_bilateral.toy.volume``: a heterogeneous participating medium (main paper Figs. 8-9).
* ``optax_bilateral.toy.triangle_mesh``: the mesh scenes (main paper Fig. 10).

Import the module you need; the toy renderers may use scikit-image and scipy, and
the optimizer library never imports them.
"""
