"""Developer tools: A/B timing, profiling and cost probes. Not installed; run from a checkout.
They may import ``experiments`` (its instruments and setups); ``experiments`` never imports them."""
