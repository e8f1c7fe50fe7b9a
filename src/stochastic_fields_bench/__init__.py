"""Experiment code above the library: the benchmark tables (``tables``) and the speed-against-error
benchmark (``speed``). The library (``stochastic_fields``) never imports this package."""
