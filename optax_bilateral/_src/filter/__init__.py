"""The a-trous cross-bilateral filter: its definition, its kernels and its front door.

The lowest layer above ``validation`` and ``numerics``; the rules and the optimizer call it.
"""
