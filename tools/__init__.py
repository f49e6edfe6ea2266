"""Developer tools: A/B timing, profiling, cost probes, and helpers the tests and
benchmarks share (compile counting, HLO collectives). Not installed; run from a checkout."""
