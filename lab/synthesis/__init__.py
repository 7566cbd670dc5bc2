"""Synthesis measurements and remedies the benchmarks use: texture oracles, footage
coefficients, masked image metrics, optical-flow refinement of the examples' alignment."""
