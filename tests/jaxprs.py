"""Walking a jaxpr, for the tests that count what a traced program holds."""


def eqns(jaxpr):
    """Every equation of ``jaxpr`` and of the jaxprs inside it (conditionals' branches, inner
    jits, custom rules), depth first."""
    for eqn in jaxpr.eqns:
        yield eqn
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                sub = getattr(sub, "jaxpr", sub)
                if hasattr(sub, "eqns"):
                    yield from eqns(sub)
