"""Toy differentiable renderers with genuine Monte Carlo gradient noise (JAX, CPU-friendly).

``optax_bilateral.toy.texture``: a glossy plane with a GGX roughness texture lit by
an environment, for the paper's texture-recovery experiment (main paper Fig. 5).
The toy renderers may use scikit-image and scipy; the optimizer library never imports them.
"""
