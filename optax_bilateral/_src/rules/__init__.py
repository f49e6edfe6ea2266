"""The sigma_d rules: the protocol the per-leaf step calls, ``Fixed``, ``Auto``, ``Sure`` and
the registry of shorthands."""
